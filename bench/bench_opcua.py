"""OPC UA beside Modbus under load, and under hostile input.

    python bench/bench_opcua.py [--loops 1000] [--clients 10] [--seconds 10] [--rounds 3] [--hostile 100000]

**Load.** The device (``--loops`` loops of a fleet, tick 0.1 s, real time, PV measurement noise on every loop
so that PV and OP change at every tick) and its OPC UA server run in this process, in one event loop, as
``valve-emulator serve --opcua`` runs them. A second process opens ``--clients`` OPC UA sessions (asyncua),
each with one subscription (publishing interval 100 ms) monitoring every loop's ``pv`` and ``op``, and one
Modbus client polling 125 holding registers at 10 Hz. Over a ``--seconds`` window: the tick's lateness
against its absolute deadline (p50, p99; target p99 <= 5 ms) and the notifications each client received
against the expected ``2 × loops × seconds / 0.1 s`` (a changed value per item per publishing interval;
target >= 95 %). Medians over ``--rounds``.

**Hostile.** ``--hostile N`` malformed OPC UA messages (``tests/opcua/hostile.py``: random bytes, absurd
and tiny sizes, garbage after Hello, truncated chunks, bad sequence numbers, junk OpenSecureChannel, TLS
ClientHello) from 4 threads of another process while the device ticks and a Modbus client and an OPC UA
client read once a second: crashes, ticks per second, overruns, normal reads answered.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "tests" / "opcua"))

from bench_scale import fleet_mapping  # noqa: E402
from common import machine, table  # noqa: E402

PUBLISH_MS = 100


def _clients(url: str, modbus_port: int, loops: list[str], clients: int, seconds: float, out_q) -> None:
    """``clients`` OPC UA sessions subscribed to every loop's pv and op, and a Modbus poller, for ``seconds``."""
    import logging

    from asyncua import Client
    from pymodbus.client import AsyncModbusTcpClient

    logging.basicConfig(level=logging.ERROR)
    for name in ("pymodbus", "asyncua"):
        logging.getLogger(name).setLevel(logging.ERROR)

    async def session(counts, i, ready):
        client = Client(url, timeout=60)
        async with client:
            ns = await client.get_namespace_index("urn:valve-emulator")

            class Handler:
                def datachange_notification(self, node, val, data):
                    counts[i] += 1

            sub = await client.create_subscription(PUBLISH_MS, Handler())
            nodes = [client.get_node(f"ns={ns};s={path}.{var}") for path in loops for var in ("pv", "op")]
            for k in range(0, len(nodes), 500):
                await sub.subscribe_data_change(nodes[k:k + 500])
            ready.set()
            await asyncio.sleep(3600)

    async def poll(count):
        client = AsyncModbusTcpClient("127.0.0.1", port=modbus_port, timeout=2, retries=0)
        await client.connect()
        try:
            while True:
                rr = await client.read_holding_registers(0, count=125, device_id=1)
                count[0] += not rr.isError()
                await asyncio.sleep(0.1)
        finally:
            client.close()

    async def main():
        counts, polled = [0] * clients, [0]
        ready = [asyncio.Event() for _ in range(clients)]
        tasks = []
        for i in range(clients):    # one at a time: a session and its subscription, then the next
            tasks.append(asyncio.create_task(session(counts, i, ready[i])))
            await asyncio.wait_for(ready[i].wait(), 600)
        tasks.append(asyncio.create_task(poll(polled)))
        await asyncio.sleep(2.0)                       # initial values and the first publishes settle
        start = list(counts)
        out_q.put(("start", time.time()))
        await asyncio.sleep(seconds)
        out_q.put(("counts", [c - s for c, s in zip(counts, start)], polled[0]))
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(main())


async def _load_round(n: int, clients: int, seconds: float) -> dict:
    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.server import EmulatorServer
    from valve_emulator.opcua import OpcUaServer

    cfg = server_from_mapping(fleet_mapping(n))
    async with EmulatorServer(cfg, port=0, time_scale=1.0) as srv:
        for i in range(n):
            srv.device.bank.set_noise(i, 0.05)
        t0 = time.monotonic()
        async with OpcUaServer(srv.device, loops=cfg.loops, port=0) as opc:
            build = time.monotonic() - t0
            paths = [f"Unit{srv.device.units[i]}.{lp.name}" for i, lp in enumerate(cfg.loops)]
            q = mp.Queue()
            proc = mp.Process(target=_clients, args=(opc.url, srv.port, paths, clients, seconds, q), daemon=True)
            proc.start()
            loop = asyncio.get_running_loop()
            msg = await loop.run_in_executor(None, q.get, True, 900)
            assert msg[0] == "start"
            srv.device.jitter = type(srv.device.jitter)(4096)
            ticks0, overruns0, sent0, t0 = srv.device.ticks, srv.device.overruns, opc.notifications, time.monotonic()
            msg = await loop.run_in_executor(None, q.get, True, seconds + 300)
            elapsed = time.monotonic() - t0
            ticks, overruns = srv.device.ticks - ticks0, srv.device.overruns - overruns0
            lateness = srv.device.jitter.values()
            proc.join(30)
            if proc.is_alive():
                proc.kill()
            counts, polled = msg[1], msg[2]
    expected = 2 * n * seconds * 1000 / PUBLISH_MS
    import numpy as np

    return {"build": build, "p50": float(np.percentile(lateness, 50)) * 1e3,
            "p99": float(np.percentile(lateness, 99)) * 1e3, "ticks": ticks / elapsed, "overruns": overruns,
            "received": min(counts) / expected, "received_median": statistics.median(counts) / expected,
            "handed": (opc.notifications - sent0) / clients / (expected * elapsed / seconds),
            "polled": polled / seconds}


def _attack_process(url: str, count: int, out_q) -> None:
    from hostile import attack

    out_q.put(attack("127.0.0.1", int(url.rsplit(":", 1)[1].split("/")[0]), url, count))


async def _hostile(count: int) -> dict:
    from asyncua import Client
    from pymodbus.client import AsyncModbusTcpClient

    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.server import EmulatorServer
    from valve_emulator.opcua import OpcUaServer

    cfg = server_from_mapping(fleet_mapping(10))
    async with EmulatorServer(cfg, port=0, time_scale=1.0) as srv, \
            OpcUaServer(srv.device, loops=cfg.loops, port=0) as opc:
        q = mp.Queue()
        ticks0, overruns0, t0 = srv.device.ticks, srv.device.overruns, time.monotonic()
        proc = mp.Process(target=_attack_process, args=(opc.url, count, q), daemon=True)
        proc.start()
        reads = failures = 0
        path = f"Unit{srv.device.units[0]}.{cfg.loops[0].name}"
        async with Client(opc.url) as client, AsyncModbusTcpClient("127.0.0.1", port=srv.port) as mb:
            ns = await client.get_namespace_index("urn:valve-emulator")
            pv = client.get_node(f"ns={ns};s={path}.pv")
            while proc.is_alive():
                try:
                    await pv.read_value()
                    rr = await mb.read_holding_registers(0, count=31, device_id=srv.device.units[0])
                    reads += 1
                    failures += rr.isError()
                except Exception:
                    failures += 1
                await asyncio.sleep(1.0)
        sent = q.get(timeout=60)
        elapsed = time.monotonic() - t0
        return {"sent": sum(sent[k] for k in sent if k not in ("closed_by_server", "seconds")),
                "closed": sent["closed_by_server"], "seconds": sent["seconds"],
                "ticks": (srv.device.ticks - ticks0) / elapsed, "overruns": srv.device.overruns - overruns0,
                "error": srv.device.error, "reads": reads, "failures": failures}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--loops", type=int, default=1000)
    p.add_argument("--clients", type=int, default=10)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--hostile", type=int, default=100_000)
    args = p.parse_args(argv)
    print(machine())
    rounds = [asyncio.run(_load_round(args.loops, args.clients, args.seconds)) for _ in range(args.rounds)]
    med = {k: statistics.median(r[k] for r in rounds) for k in rounds[0]}
    print(f"\nLoad: {args.loops} loops at 10 Hz, {args.clients} OPC UA clients subscribed to every loop's pv and op "
          f"(publishing {PUBLISH_MS} ms), one Modbus poller at 10 Hz; {args.seconds:g} s windows, "
          f"median of {args.rounds}")
    print(table([("address space build", f"{med['build']:.1f} s"),
                 ("tick lateness p50 / p99", f"{med['p50']:.1f} / {med['p99']:.1f} ms (target p99 <= 5 ms)"),
                 ("ticks per second, overruns", f"{med['ticks']:.2f}, {med['overruns']:.0f}"),
                 ("notifications received, worst client",
                  f"{100 * med['received']:.1f} % of expected (target >= 95 %)"),
                 ("notifications received, median client", f"{100 * med['received_median']:.1f} %"),
                 ("handed to each subscription by the server", f"{100 * med['handed']:.1f} %"),
                 ("Modbus polls answered per second", f"{med['polled']:.1f}")], ("figure", "value")))
    if args.hostile:
        h = asyncio.run(_hostile(args.hostile))
        print(f"\nHostile: {h['sent']:,} malformed OPC UA messages in {h['seconds']:.0f} s "
              f"({h['sent'] / h['seconds']:,.0f}/s) from 4 threads of another process")
        print(table([("connections the server closed itself", f"{h['closed']:,}"),
                     ("ticks per second during the attack", f"{h['ticks']:.2f} (target 10 ± 1)"),
                     ("overruns", str(h["overruns"])), ("tick task failed", str(h["error"] is not None)),
                     ("normal reads (OPC UA + Modbus, 1/s) / failures", f"{h['reads']} / {h['failures']}")],
                    ("figure", "value")))


if __name__ == "__main__":
    main()
