"""Normal clients' throughput while hostile connections send garbage.

Run: ``python bench/bench_modbus_under_garbage.py [--seconds 3] [--rounds 5] [--normal 4] [--hostile 50]``.

The emulator (one loop, time-scale 1, 100 ms tick) runs in its own process. Normal clients (this process,
raw sockets, one outstanding 10-register read each, as fast as answers come) are measured alternately
without and with ``--hostile`` connections run by a third process, in the same run; the medians over the
rounds give the ratio ``with / without`` (target >= 0.7). Two kinds of garbage:

- ``random``: random bytes. The server closes such a connection at the first header it cannot parse;
  the hostile client reconnects at once and sends more, so this is also a connect/close storm.
- ``framed``: well-formed MBAP frames with malformed PDUs (a read of 0 registers), pipelined 32 at a
  time, answers read and thrown away: garbage the server must answer (exception 0x03), not just drop.
- ``churn`` (for information, beyond the issue's case): random bytes, then the hostile client hangs up
  itself and reconnects at once: a connect/close storm that no tarpit can slow down.

The tick's lateness p50/p99 (over the whole run), the server's counters and each process's CPU share
while under attack are reported too. All three processes share this machine's CPUs, so with fewer than
three cores the hostile process also takes CPU time away from the others; the table says how many cores
there were. ``--no-defences`` runs the same with the tarpit and the error budget switched off, for
comparison.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import os
import random
import selectors
import socket
import statistics
import struct
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import table  # noqa: E402

READ = struct.pack(">HHHBBHH", 0, 0, 6, 1, 3, 0, 10)
BAD_READ = struct.pack(">HHHBBHH", 0, 0, 6, 1, 3, 0, 0)   # quantity 0: exception 0x03


def _serve(port_q, stop_ev, stats_q, defences: bool = True) -> None:
    async def main():
        import numpy as np

        from valve_emulator.config import server_from_mapping
        from valve_emulator.device import connection
        from valve_emulator.device.server import EmulatorServer

        device = {"tick": 0.1}
        if not defences:  # for comparison: no tarpit, no error budget (fairness per turn stays)
            connection.VIOLATION_DELAY = 0.0
            device["error_rate"] = 1.0e+9
        cfg = server_from_mapping({"device": device, "loops": [
            {"unit": 1, "valve": {"S": 5.0, "J": 2.0}, "plant": {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0}}]})
        async with EmulatorServer(cfg, time_scale=1.0) as srv:
            import gc
            gc.freeze()   # as `valve-emulator serve` does
            port_q.put(srv.port)
            while not stop_ev.is_set():
                await asyncio.sleep(0.05)
            late = srv.device.jitter.values()
            stats_q.put({"p50": float(np.percentile(late, 50)), "p99": float(np.percentile(late, 99)),
                         "ticks": srv.device.ticks, "overruns": srv.device.overruns, "requests": srv.requests,
                         "violations": srv.violations, "refused": srv.guard.refused,
                         "throttled": srv.throttled})

    import logging
    logging.disable(logging.WARNING)  # the rate-limited warnings are part of the load, not of the report
    asyncio.run(main())


def _hostile(port: int, n: int, kind: str, run_ev, stop_ev, stats_q, seed: int = 9) -> None:
    """``n`` connections sending garbage whenever ``run_ev`` is set; reconnect whenever closed."""
    rng = random.Random(seed)
    chunks = [BAD_READ * 32] if kind == "framed" else [rng.randbytes(512) for _ in range(64)]
    sel = selectors.DefaultSelector()
    stats = {"connects": 0, "bytes": 0}

    def connect():
        s = socket.socket()
        # The server reads at most its own socket buffer (64 KiB) from a connection it is tarpitting or
        # throttling; what a remote attacker queues beyond that sits on the attacker's machine. Co-located
        # here, a 4 MB send buffer (Linux autotuning) per connection would only burn this machine's CPU on
        # copies the server never sees, so keep the attacker's buffer at the server's size.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 64 * 1024)
        s.setblocking(False)
        s.connect_ex(("127.0.0.1", port))
        sel.register(s, selectors.EVENT_READ | selectors.EVENT_WRITE)
        stats["connects"] += 1

    def drop(s):
        sel.unregister(s)
        s.close()

    while not stop_ev.is_set():
        if not run_ev.wait(0.05):
            for key in list(sel.get_map().values()):
                drop(key.fileobj)
            continue
        while len(sel.get_map()) < n:
            connect()
        for key, events in sel.select(0.05):
            s = key.fileobj
            try:
                if events & selectors.EVENT_READ and not s.recv(65536):
                    drop(s)
                    continue
                if events & selectors.EVENT_WRITE:
                    stats["bytes"] += s.send(rng.choice(chunks))
                    if kind == "churn":   # hang up at once and come back: a connect/close storm
                        drop(s)
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                drop(s)
    stats_q.put(stats)


async def _normal(port: int, seconds: float, drops: list) -> int:
    """Answers received by one polling client in ``seconds``; reconnects (counted in ``drops``) like a SCADA."""
    n = 0
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            while time.perf_counter() < end:
                writer.write(struct.pack(">H", n & 0xFFFF) + READ[2:])
                header = await reader.readexactly(7)
                body = await reader.readexactly(struct.unpack(">H", header[4:6])[0] - 1)
                assert body[:2] == b"\x03\x14", body
                n += 1
            writer.close()
            await writer.wait_closed()
        except (ConnectionError, asyncio.IncompleteReadError):
            drops.append(time.perf_counter())
            await asyncio.sleep(0.01)
    return n


def _throughput(port: int, conns: int, seconds: float, drops: list | None = None) -> float:
    drops = [] if drops is None else drops

    async def run():
        return sum(await asyncio.gather(*[_normal(port, seconds, drops) for _ in range(conns)]))
    return asyncio.run(run()) / seconds


def _cpu(pid: int) -> float:
    """CPU seconds (user + system) used so far by process ``pid`` (Linux ``/proc``; 0 elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _phase(port: int, normal: int, seconds: float, pids: list[int], drops: list) -> tuple[float, list[float]]:
    """Normal clients' req/s and the CPU share (0..1 of one core) of each process in ``pids`` meanwhile."""
    before, t0 = [_cpu(p) for p in pids], time.perf_counter()
    rate = _throughput(port, normal, seconds, drops)
    wall = time.perf_counter() - t0
    return rate, [(_cpu(p) - b) / wall for p, b in zip(pids, before)]


def measure(kind: str, *, seconds: float, rounds: int, normal: int, hostile: int, defences: bool = True) -> dict:
    ctx = mp.get_context("spawn")
    port_q, stats_q, hostile_q = ctx.Queue(), ctx.Queue(), ctx.Queue()
    stop_ev, run_ev = ctx.Event(), ctx.Event()
    server = ctx.Process(target=_serve, args=(port_q, stop_ev, stats_q, defences), daemon=True)
    server.start()
    port = port_q.get(timeout=120)
    attacker = ctx.Process(target=_hostile, args=(port, hostile, kind, run_ev, stop_ev, hostile_q), daemon=True)
    attacker.start()
    try:
        _throughput(port, normal, 1.0)                      # warm-up
        pids = [server.pid, os.getpid(), attacker.pid]
        quiet, loud, drops = [], [], []
        for _ in range(rounds):
            run_ev.clear()
            time.sleep(0.3)                                  # let the hostile connections go away
            quiet.append(_phase(port, normal, seconds, pids, []))
            run_ev.set()
            time.sleep(0.3)                                  # let the hostile load build up
            loud.append(_phase(port, normal, seconds, pids, drops))
    finally:
        run_ev.clear()
        stop_ev.set()
        server_stats = stats_q.get(timeout=60)
        hostile_stats = hostile_q.get(timeout=60)
        server.join(30)
        attacker.join(30)
    q, h = statistics.median(r for r, _ in quiet), statistics.median(r for r, _ in loud)
    cpu = [statistics.median(c[i] for _, c in loud) for i in range(3)]
    return {"kind": kind, "quiet": q, "loud": h, "ratio": h / q, "cpu": cpu, "drops": len(drops), **server_stats,
            **hostile_stats}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="seconds per measurement (default 3)")
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds (default 5)")
    ap.add_argument("--normal", type=int, default=4, help="normal client connections (default 4)")
    ap.add_argument("--hostile", type=int, default=50, help="hostile connections (default 50)")
    ap.add_argument("--kind", choices=("random", "framed", "churn", "all"), default="all")
    ap.add_argument("--no-defences", action="store_true",
                    help="for comparison: run the server without the tarpit and the error budget")
    args = ap.parse_args(argv)
    kinds = ("random", "framed", "churn") if args.kind == "all" else (args.kind,)
    rows = []
    for kind in kinds:
        r = measure(kind, seconds=args.seconds, rounds=args.rounds, normal=args.normal, hostile=args.hostile,
                    defences=not args.no_defences)
        name = kind + (" (no defences)" if args.no_defences else "")
        rows.append((name, f"{r['quiet']:,.0f}", f"{r['loud']:,.0f}", f"{r['ratio']:.2f}",
                     " / ".join(f"{c:.0%}" for c in r["cpu"]), f"{r['connects']:,}", f"{r['bytes'] / 1e6:,.1f}",
                     f"{r['violations']:,} / {r['throttled']:,}", f"{r['refused']:,} / {r['drops']}",
                     f"{r['p50'] * 1e3:.2f} / {r['p99'] * 1e3:.2f}", r["overruns"]))
    print(f"## Normal clients ({args.normal} connections, 10-register reads) against {args.hostile} hostile "
          f"connections; medians of {args.rounds} rounds of {args.seconds:g} s; {os.cpu_count()} CPUs\n")
    print(table(rows, ("garbage", "req/s without", "req/s with", "ratio (target >= 0.7)",
                       "CPU with: server / normal clients / hostile", "hostile connects", "hostile MB sent",
                       "tarpitted / throttled", "refused connections / normal clients dropped",
                       "tick lateness p50 / p99 ms", "overruns")))


if __name__ == "__main__":
    main()
