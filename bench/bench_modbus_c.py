"""Benchmark: the emulator's Modbus TCP server against the libmodbus C server, one process against one process.

Both serve 10-register reads (FC3) to the libmodbus C load client (``bench/c/modbus_load.c``: one request
outstanding per connection), on 1 and on 10 connections; the emulator with uvloop, in one process and in two
(``--processes 2``, five connections on each). The servers take turns within each round, so every ratio
compares figures measured a few seconds apart; the table gives each configuration's median over the rounds
with its range (the noise of this shared 2-core machine), and the median of the per-round ratios. Run::

    python bench/bench_modbus_c.py [--seconds 3] [--rounds 3]

Needs gcc, pkg-config and libmodbus-dev (the C server is libmodbus' own ``bandwidth-server-many-up`` example,
a single select loop) and uvloop.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scale import _yaml, c_load_all  # noqa: E402
from common import LIBMODBUS_EXAMPLES, build_c, machine, start_serve, stop, table  # noqa: E402

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="seconds per measurement (3)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds, servers in turn within each (3)")
    args = ap.parse_args(argv)
    print(machine())
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        client = build_c(HERE / "c" / "modbus_load.c", tmp / "modbus_load")
        server = build_c(LIBMODBUS_EXAMPLES / "bandwidth-server-many-up.c", tmp / "bandwidth_server")
        if client is None or server is None:
            return 1
        two = _yaml({"device": {"tick": 0.1}, "loops": [
            {"unit": u, "valve": {"S": 5.0, "J": 2.0},
             "plant": {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0}} for u in (1, 2)]}, tmp / "two.yaml")
        procs = []
        try:
            one, ports1 = start_serve(str(two), "--port", "0", "--uvloop")
            procs.append(one)
            both, ports2 = start_serve(str(two), "--port", "0", "--uvloop", "--processes", "2")
            procs.append(both)
            cserver = subprocess.Popen([str(server)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            procs.append(cserver)
            time.sleep(0.5)   # it prints nothing when ready; a probe would take one of its accept slots
            servers = {"emulator, uvloop, 1 process": [(ports1[0], 1), (ports1[0], 2)],
                       "emulator, uvloop, 2 processes": [(ports2[0], 1), (ports2[1], 2)],
                       "libmodbus C server": [(1502, 1)]}
            got: dict[tuple[int, str], list[dict]] = {}
            for conns in (1, 10):
                for _ in range(args.rounds):
                    for name, targets in servers.items():
                        if len(targets) > conns and name.endswith("2 processes"):
                            continue   # one connection cannot load two processes
                        r = c_load_all(client, targets[:conns] if conns == 1 else targets, conns, args.seconds)
                        got.setdefault((conns, name), []).append(r)
        finally:
            for p in procs:
                stop(p)
    rows = []
    for (conns, name), runs in got.items():
        c_runs = got[(conns, "libmodbus C server")]
        rates = [r["rate"] for r in runs]
        ratios = [r["rate"] / c["rate"] for r, c in zip(runs, c_runs)]
        rows.append((conns, name, f"{statistics.median(rates):,.0f}", f"{min(rates):,.0f}–{max(rates):,.0f}",
                     f"{statistics.median(r['p50_ms'] for r in runs):.3f}",
                     f"{statistics.median(r['p99_ms'] for r in runs):.3f}",
                     f"{statistics.median(ratios):.2f}", f"{min(ratios):.2f}–{max(ratios):.2f}"))
    print(f"\n{args.rounds} rounds of {args.seconds:g} s, servers in turn; medians, ranges over the rounds\n")
    print(table(rows, ("conns", "server", "req/s", "range", "p50 ms", "p99 ms", "× C server", "ratio range")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
