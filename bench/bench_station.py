"""The instructor station under load: tick lateness of a 1,000-loop fleet with browsers and Modbus clients.

    python bench/bench_station.py [--loops 1000] [--seconds 5] [--rounds 3] [--sse 10] [--modbus 10]

The device and its station run in this process, in one event loop, as ``valve-emulator serve --web``
runs them (tick 0.1 s, real time). A second process opens ``--sse`` server-sent-event streams (what the
pages use: ``/api/stream`` at 10 states/s; with a fleet, the first 50 loops) and ``--modbus`` Modbus TCP
clients, each reading 125 holding registers at 10 Hz. Measured over ``--seconds`` windows, ``--rounds``
times, once without clients (baseline) and once with them: the lateness of each tick against its absolute
deadline (p50, p99; target p99 <= 5 ms), the tick's own compute time (steps, register image, station
evaluation), and what the clients received. Figures are medians over the rounds.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import multiprocessing as mp
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_scale import fleet_mapping  # noqa: E402
from common import machine, table  # noqa: E402


def _clients(web_port: int, modbus_port: int, units: list[int], sse: int, modbus: int, seconds: float, out_q) -> None:
    """The load: ``sse`` event streams and ``modbus`` pollers at 10 Hz for ``seconds``; reports counts."""
    import aiohttp
    from pymodbus.client import AsyncModbusTcpClient

    async def stream(session, counts, i):
        async with session.get(f"http://127.0.0.1:{web_port}/api/stream?rate=10&view=trainee") as resp:
            async for line in resp.content:
                if line.startswith(b"data: "):
                    counts[i] += 1

    async def poll(counts, i):
        client = AsyncModbusTcpClient("127.0.0.1", port=modbus_port, timeout=2, retries=0)
        await client.connect()
        unit = units[i % len(units)]
        next_t = time.monotonic()
        try:
            while True:
                rr = await client.read_holding_registers(0, count=125, device_id=unit)
                if not rr.isError():
                    counts[i] += 1
                next_t += 0.1
                await asyncio.sleep(max(next_t - time.monotonic(), 0.0))
        finally:
            client.close()

    async def main():
        sse_counts, mb_counts = [0] * sse, [0] * modbus
        async with aiohttp.ClientSession() as session:
            tasks = [asyncio.create_task(stream(session, sse_counts, i)) for i in range(sse)]
            tasks += [asyncio.create_task(poll(mb_counts, i)) for i in range(modbus)]
            await asyncio.sleep(seconds)
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        out_q.put({"sse_events_per_s": sum(sse_counts) / seconds / max(sse, 1),
                   "modbus_reads_per_s": sum(mb_counts) / seconds / max(modbus, 1)})

    asyncio.run(main())


async def _measure(dev, seconds: float) -> dict:
    from valve_emulator.device.tick import JitterBuffer

    dev.jitter, dev.tick_time = JitterBuffer(65536), JitterBuffer(65536)
    ticks, overruns = dev.ticks, dev.overruns
    await asyncio.sleep(seconds)
    return {"p50": dev.jitter.p50 * 1e3, "p99": dev.jitter.p99 * 1e3, "compute_p50": dev.tick_time.p50 * 1e3,
            "compute_p99": dev.tick_time.p99 * 1e3, "ticks": dev.ticks - ticks, "overruns": dev.overruns - overruns}


async def run(loops: int, seconds: float, rounds: int, sse: int, modbus: int) -> dict:
    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.server import EmulatorServer
    from valve_emulator.device.snapshots import BacktrackRing, SnapshotStore
    from valve_emulator.station.app import start_station
    from valve_emulator.station.core import Station

    cfg = server_from_mapping(fleet_mapping(loops))
    async with EmulatorServer(cfg, time_scale=1.0) as srv:
        station = Station(srv.device, snapshots=SnapshotStore(), backtrack=BacktrackRing(60.0, 30))
        runner, web_port = await start_station(station, host="127.0.0.1", port=0)
        gc.freeze()
        units = sorted(set(srv.device.units))
        await asyncio.sleep(1.0)   # settle (compiled kernels warm)
        quiet, loaded, seen = [], [], []
        ctx = mp.get_context("spawn")
        for _ in range(rounds):
            quiet.append(await _measure(srv.device, seconds))
            out_q = ctx.Queue()
            proc = ctx.Process(target=_clients, args=(web_port, srv.port, units, sse, modbus, seconds + 3.0, out_q))
            proc.start()
            await asyncio.sleep(2.0)   # clients connected and streaming
            loaded.append(await _measure(srv.device, seconds))
            while proc.is_alive():
                await asyncio.sleep(0.1)
            seen.append(out_q.get())
        await runner.cleanup()
    med = lambda rows, key: statistics.median(r[key] for r in rows)  # noqa: E731
    return {"quiet": {k: med(quiet, k) for k in quiet[0]}, "loaded": {k: med(loaded, k) for k in loaded[0]},
            "clients": {k: med(seen, k) for k in seen[0]}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=1000)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--sse", type=int, default=10)
    ap.add_argument("--modbus", type=int, default=10)
    args = ap.parse_args(argv)
    res = asyncio.run(run(args.loops, args.seconds, args.rounds, args.sse, args.modbus))
    print(f"# Instructor station under load ({machine()})\n")
    print(f"{args.loops:,} loops, tick 0.1 s; {args.rounds} rounds of {args.seconds:g} s; medians.\n")
    rows = []
    for name, r in (("no clients", res["quiet"]), (f"{args.sse} SSE + {args.modbus} Modbus clients", res["loaded"])):
        rows.append((name, f"{r['p50']:.2f}", f"{r['p99']:.2f}", f"{r['compute_p50']:.2f}", f"{r['compute_p99']:.2f}",
                     f"{r['overruns']:.0f}", "yes" if r["p99"] <= 5.0 else "NO"))
    print(table(rows, ("load", "lateness p50 (ms)", "lateness p99 (ms)", "tick compute p50 (ms)",
                       "tick compute p99 (ms)", "overruns", "p99 <= 5 ms")))
    c = res["clients"]
    print(f"\nclients received: {c['sse_events_per_s']:.1f} SSE states/s per stream, "
          f"{c['modbus_reads_per_s']:.1f} Modbus reads/s per client")
    return 0


if __name__ == "__main__":
    sys.exit(main())
