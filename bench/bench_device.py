"""Speed of the Modbus device. Run: ``python bench/bench_device.py [--seconds 5]``.

1. Requests/s of the emulator against a plain pymodbus 3.16 ``SimDevice`` server, measured in the same run
   with the same clients: the pymodbus async client and a lean raw-socket client, one outstanding
   10-register read at a time, 1 and 10 connections. Each server runs in its own process, the clients in
   this one; servers are measured alternately, several rounds, medians reported.
2. Tick jitter (lateness of each tick against its absolute deadline), p50/p99, with 1,000 devices (five
   servers of 200 loops in one process, one unit id per loop) ticking at 10 Hz while 10 clients poll.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import statistics
import struct
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import table  # noqa: E402

N_REGISTERS = 28


def _plant_loops(n, first_unit=1):
    return [{"unit": first_unit + i, "valve": {"S": 5.0, "J": 2.0},
             "plant": {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0}} for i in range(n)]


def _serve(kind: str, port_q, stop_ev, stats_q=None, servers: int = 1, loops: int = 1) -> None:
    async def main():
        if kind == "plain":
            from pymodbus.server import ModbusTcpServer
            from pymodbus.simulator import DataType, SimData, SimDevice

            srv = ModbusTcpServer(SimDevice(1, simdata=[SimData(0, count=N_REGISTERS, values=0,
                                                                datatype=DataType.REGISTERS)]),
                                  address=("127.0.0.1", 0))
            await srv.serve_forever(background=True)
            port_q.put([srv.transport.sockets[0].getsockname()[1]])
            while not stop_ev.is_set():
                await asyncio.sleep(0.05)
            await srv.shutdown()
            return
        from valve_emulator.config import server_from_mapping
        from valve_emulator.device.server import EmulatorServer

        srvs = []
        for _ in range(servers):
            cfg = server_from_mapping({"device": {"tick": 0.1}, "loops": _plant_loops(loops)})
            srv = EmulatorServer(cfg, time_scale=1.0)
            await srv.start()
            srvs.append(srv)
        port_q.put([s.port for s in srvs])
        while not stop_ev.is_set():
            await asyncio.sleep(0.05)
        if stats_q is not None:
            import numpy as np

            late = np.concatenate([s.device.jitter.values() for s in srvs])
            stats_q.put({"p50": float(np.percentile(late, 50)), "p99": float(np.percentile(late, 99)),
                         "ticks": sum(s.device.ticks for s in srvs),
                         "overruns": sum(s.device.overruns for s in srvs)})
        for s in srvs:
            await s.stop()

    asyncio.run(main())


class Server:
    def __init__(self, kind, **kw):
        self.port_q, self.stop_ev, self.stats_q = mp.Queue(), mp.Event(), mp.Queue()
        self.proc = mp.Process(target=_serve, args=(kind, self.port_q, self.stop_ev, self.stats_q), kwargs=kw,
                               daemon=True)

    def __enter__(self):
        self.proc.start()
        self.ports = self.port_q.get(timeout=60)
        return self

    def __exit__(self, *exc):
        self.stop_ev.set()
        try:
            self.stats = self.stats_q.get(timeout=30)
        except Exception:
            self.stats = None
        self.proc.join(timeout=30)


async def _raw_client(port, seconds, unit=1):
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    n, lat = 0, []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        writer.write(struct.pack(">HHHBBHH", n & 0xFFFF, 0, 6, unit, 3, 0, 10))
        header = await reader.readexactly(7)
        await reader.readexactly(struct.unpack(">H", header[4:6])[0] - 1)
        lat.append(time.perf_counter() - t0)
        n += 1
    writer.close()
    return n, lat


async def _pymodbus_client(port, seconds, unit=1):
    from pymodbus.client import AsyncModbusTcpClient

    c = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
    await c.connect()
    n, lat = 0, []
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        rr = await c.read_holding_registers(0, count=10, device_id=unit)
        assert not rr.isError()
        lat.append(time.perf_counter() - t0)
        n += 1
    c.close()
    return n, lat


async def _load(client, port, conns, seconds):
    results = await asyncio.gather(*[client(port, seconds) for _ in range(conns)])
    n = sum(r[0] for r in results)
    lat = sorted(x for r in results for x in r[1])
    return n / seconds, lat[len(lat) // 2] * 1e3, lat[int(len(lat) * 0.99)] * 1e3


def throughput(seconds: float, rounds: int) -> list[tuple]:
    rows = []
    with Server("plain") as plain, Server("ours") as ours:
        for cname, client in (("pymodbus client", _pymodbus_client), ("raw socket client", _raw_client)):
            for conns in (1, 10):
                res = {"plain": [], "ours": []}
                for _ in range(rounds):
                    for kind, srv in (("plain", plain), ("ours", ours)):
                        res[kind].append(asyncio.run(_load(client, srv.ports[0], conns, seconds)))
                med = {k: [statistics.median(x[i] for x in v) for i in range(3)] for k, v in res.items()}
                rows.append((cname, conns, f"{med['plain'][0]:,.0f}", f"{med['ours'][0]:,.0f}",
                             f"{med['ours'][0] / med['plain'][0]:.2f}",
                             f"{med['ours'][1]:.2f} / {med['ours'][2]:.2f}"))
    return rows


def jitter(seconds: float) -> tuple:
    with Server("ours", servers=5, loops=200) as srv:
        async def poll_all():
            clients = [_pymodbus_client(srv.ports[i % 5], seconds, unit=1 + (7 * i) % 200) for i in range(10)]
            return await asyncio.gather(*clients)

        polled = asyncio.run(poll_all())
    st = srv.stats
    return (1000, f"{sum(p[0] for p in polled) / seconds:,.0f}", st["ticks"], st["overruns"],
            f"{st['p50'] * 1e3:.2f}", f"{st['p99'] * 1e3:.2f}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="seconds per measurement (default 3)")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds per case (default 3)")
    args = ap.parse_args(argv)
    rows = throughput(args.seconds, args.rounds)
    print("## Modbus throughput, 10-register reads (median of rounds)\n")
    print(table(rows, ("client", "connections", "plain pymodbus req/s", "emulator req/s", "ratio",
                       "emulator latency p50 / p99 ms")))
    print("\n## Tick jitter, devices ticking at 10 Hz while 10 clients poll\n")
    print(table([jitter(max(10.0, 4 * args.seconds))], ("devices", "client req/s", "ticks", "overruns",
                                                         "lateness p50 ms", "lateness p99 ms")))


if __name__ == "__main__":
    main()
