"""Hostile input on every interface of one running emulator (HTTP station, RTU serial line, snapshot files,
SIGHUP with a broken config): zero crashes, the tick on schedule, normal reads correct afterwards.

Run: ``python bench/bench_interfaces_under_attack.py [--size full|ci] [--phase NAME ...]`` (full: about ten
minutes). The attacks and what each phase checks are ``tests/hostile_input.py`` (the same stress the test
``tests/system/test_hostile_input.py`` runs at CI size); this prints their figures as a table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
from common import machine, table  # noqa: E402
from hostile_input import CI, FULL, PHASES, run  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=("full", "ci"), default="full")
    ap.add_argument("--phase", action="append", choices=tuple(PHASES), help="run only these (repeatable)")
    args = ap.parse_args(argv)
    sizes = FULL if args.size == "full" else CI
    print(f"# hostile input, {args.size} size, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(f"# {machine()}; load average {os.getloadavg()[0]:.1f} at the start")
    results = run(sizes, tuple(args.phase or PHASES), progress=lambda f: print(json.dumps(f), flush=True))
    print(json.dumps(results[-1]))
    rows = []
    for f in results[:-1]:
        rows.append((f["phase"], f["seconds"], f.get("requests", f.get("frames", f.get("files"))),
                     f"{f['tick_min']:.2f}..{f['tick_max']:.2f}", f["tick_off"], f"{f['tick_windows']}"))
    print(table(rows, ("phase", "s", "requests/frames/files", "ticks/s (min..max)", "windows outside 9..11",
                       "windows")))
    after = results[-1]
    print(f"after: alive {after['alive']}, crashes {after['crashes']}, reads correct: Modbus {after['modbus_ok']}, "
          f"HTTP {after['http_ok']}, RTU {after['rtu_ok']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
