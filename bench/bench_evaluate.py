"""Benchmark: wall time of ``valve-emulator evaluate`` on a labelled set (target: the 80 plant windows in
≤ 5 minutes on a 2-core machine, using both cores), and of the plant-data ``diagnose`` on long recordings.

``evaluate`` is run as the user runs it (a subprocess of the installed command, so worker start-up and
imports are counted) with ``--jobs 1`` and ``--jobs N``; ``diagnose`` without a model on the proof cases'
concentration loop with concealed stiction (closed loop, only t/op/pv, PV noise), one untimed warm-up
first. Run::

    python bench/bench_evaluate.py [--set ../shared/data/stictiongpt_plant] [--jobs 1 2] [--samples 1000 10000]

Without ``--set`` only ``diagnose`` is timed (the labelled data are not part of the repository).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import table


def time_evaluate(path: Path, jobs: int) -> tuple[float, str]:
    """Seconds for ``valve-emulator evaluate PATH --jobs N`` and its per-valve summary line for our method."""
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "valve_emulator", "evaluate", str(path), "--jobs", str(jobs),
                          "--quiet"], check=True, capture_output=True, text=True).stdout
    seconds = time.perf_counter() - t
    line = next((ln for ln in out.splitlines() if ln.startswith("diagnosis")), "")
    return seconds, " ".join(line.split())


def time_diagnose(samples: int) -> float:
    """Seconds for ``valve-emulator diagnose REC.csv`` (no model) on a concealed stiction recording."""
    from valve_emulator.benchmark.cases import CASES, generate
    from valve_emulator.recordings.recording import write_csv

    case = CASES[0]
    rec, _, _ = generate(case, duration=samples - 1 + case.cut)
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "rec.csv")
        write_csv(rec, path)
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "valve_emulator", "diagnose", path, "--quiet"], check=True,
                       capture_output=True)
        return time.perf_counter() - t


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--set", type=Path, metavar="DIR_OR_INDEX",
                   help="labelled set to time evaluate on (e.g. ../shared/data/stictiongpt_plant; none: skip)")
    p.add_argument("--jobs", type=int, nargs="*", default=[1, 2], help="--jobs values to time (none: skip evaluate)")
    p.add_argument("--samples", type=int, nargs="*", default=[1000, 10000],
                   help="recording lengths for diagnose (100000 takes a few minutes)")
    args = p.parse_args(argv)
    print(f"{os.cpu_count()} CPU(s)")
    rows = []
    if args.set is None:
        print("no --set: evaluate skipped")
    elif not args.set.exists():
        p.error(f"--set {args.set}: no such file or folder")
    else:
        for jobs in args.jobs:
            seconds, line = time_evaluate(args.set, jobs)
            rows.append((f"evaluate {args.set.name} --jobs {jobs}", f"{seconds:.0f} s", line))
    if args.samples:
        time_diagnose(1000)  # warm-up: compiled kernels load from numba's cache
    for n in args.samples:
        rows.append((f"diagnose, {n} samples, no model", f"{time_diagnose(n):.1f} s", ""))
    print(table(rows, ("run", "wall time", "per-valve result (sens., spec., BA, coverage, TP FN FP TN)")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
