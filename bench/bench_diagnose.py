"""Benchmark: wall time of the diagnosis with the full candidate library (target: 10,000 samples ≤ 20 s).

The recording is the proof cases' concentration loop with concealed stiction (S = 5, J = 2, closed loop, only OP
and PV, PV noise 5 % of the amplitude); the nominal model lacks the stiction. One untimed warm-up run
loads the compiled kernels (numba caches them on disk; the first run after installation also compiles
them, which is reported separately). Run::

    python bench/bench_diagnose.py [--samples 1000 10000] [--repeat 3] [--no-model]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis.explain.pipeline import explain


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, nargs="+", default=[1000, 10000])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--no-model", action="store_true", help="identify the linear part from the data instead")
    args = p.parse_args(argv)
    case = CASES[0]  # stiction, undershoot, concentration loop, dt = 1 s
    print(f"{os.cpu_count()} CPU(s); case: {case.name}; {'no model' if args.no_model else 'nominal model given'}")
    t0 = time.perf_counter()
    rec, nominal, _ = generate(case, duration=1000 + case.cut)
    explain(rec, None if args.no_model else nominal)
    print(f"warm-up (kernel load / first-time compile): {time.perf_counter() - t0:.1f} s")
    for n in args.samples:
        rec, nominal, _ = generate(case, duration=n - 1 + case.cut)
        times, d = [], None
        for _ in range(args.repeat):
            t = time.perf_counter()
            d = explain(rec, None if args.no_model else nominal)
            times.append(time.perf_counter() - t)
        print(f"{len(rec):6d} samples: median {statistics.median(times):5.2f} s (min {min(times):.2f}, "
              f"max {max(times):.2f}) | {d.verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
