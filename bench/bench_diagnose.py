"""Benchmark: wall time of the diagnosis with the full candidate library, warm and on a first run.

The recording is the proof cases' concentration loop with concealed stiction (S = 5, J = 2, closed loop, only OP
and PV, PV noise 5 % of the amplitude); the nominal model lacks the stiction (``--no-model``: plant data, the
linear part identified). *Warm*: one untimed warm-up loads the compiled kernels (numba caches them on disk),
then the median of ``--repeat`` runs. *First run*: a fresh interpreter with an empty kernel cache
(``NUMBA_CACHE_DIR`` a new temporary folder), as after a fresh install: imports, reading the recording's CSV,
compilation and one diagnosis, timed from outside; then the same after ``valve-emulator compile`` (untimed).
``--before CHECKOUT``: on a shared machine, compare with another checkout of the project measured alternately,
each run a fresh interpreter (its code on ``PYTHONPATH``) that warms up and times one diagnosis, wall and CPU
seconds (CPU: every thread's, the less sensitive to the machine's load); medians and the ratio after/before, the
machine's load average before and after each size, and each checkout's first finding with its parameters and
95 % intervals (a speed-up must not change them). ``--first-runs`` with ``--before``: first runs after
``compile`` instead (:func:`alternate_first_runs`), with the seconds spent importing.
Run::

    python bench/bench_diagnose.py [--samples 1000 10000] [--repeat 3] [--no-model] [--no-first-run]
    python bench/bench_diagnose.py --before /path/to/other/checkout [--samples 10000] [--repeat 3] [--no-model]
    python bench/bench_diagnose.py --before /path/to/other/checkout --first-runs [--samples 10000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from valve_emulator.benchmark.cases import CASES, generate, nominal_mapping
from valve_emulator.diagnosis.explain.pipeline import explain
from valve_emulator.recordings.recording import write_csv

_FIRST_RUN = """
import json, sys
import valve_emulator as ve
from valve_emulator.config import loop_from_mapping
model = None if sys.argv[2] == "none" else loop_from_mapping(json.load(open(sys.argv[2])))
print(ve.diagnose(sys.argv[1], model).answer)
"""

# The same first run, saying where its time went: importing (the package and what the diagnosis imports), and
# how many kernels were compiled rather than loaded from the cache (none, after `compile`).
_FIRST_RUN_TIMED = """
import time
t0 = time.perf_counter()
import json, sys
import valve_emulator as ve
import valve_emulator.diagnosis.api
from valve_emulator.config import loop_from_mapping
from valve_emulator.commands.compile import kernel_cache_stats
t1 = time.perf_counter()
model = None if sys.argv[2] == "none" else loop_from_mapping(json.load(open(sys.argv[2])))
answer = ve.diagnose(sys.argv[1], model).answer
print(json.dumps({"import": t1 - t0, "total": time.perf_counter() - t0, "answer": answer,
                  "compiled": sum(m for _, m in kernel_cache_stats().values())}))
"""


def first_run(samples: int, model: bool, ahead: bool = False) -> float:
    """Seconds for a fresh interpreter with an empty kernel cache to import, compile and diagnose once.

    The recording (standard CSV) and the nominal model (JSON of the configuration mapping) are written first,
    so the child does what a user's first ``diagnose`` does — read a file, compile the diagnosis' kernels,
    diagnose — and not the simulation that made the recording. ``ahead``: ``valve-emulator compile`` runs
    first (not timed), as after an install that follows the README.
    """
    with tempfile.TemporaryDirectory() as tmp:
        csv_path, model_path = _write_inputs(tmp, samples)
        env = {**os.environ, "NUMBA_CACHE_DIR": os.path.join(tmp, "numba")}
        if ahead:
            subprocess.run([sys.executable, "-m", "valve_emulator", "compile"], env=env, check=True,
                           capture_output=True)
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", _FIRST_RUN, csv_path, model_path if model else "none"], env=env,
                       check=True, capture_output=True)
        return time.perf_counter() - t


def _write_inputs(folder: str, samples: int) -> tuple[str, str]:
    """The recording (standard CSV) and the nominal model (JSON of the configuration mapping) in ``folder``."""
    case = CASES[0]
    rec, _, _ = generate(case, duration=samples - 1 + case.cut)
    csv_path, model_path = os.path.join(folder, "loop.csv"), os.path.join(folder, "model.json")
    write_csv(rec, csv_path)
    with open(model_path, "w") as f:
        json.dump(nominal_mapping(case), f)
    return csv_path, model_path


ROOT = Path(__file__).resolve().parent.parent


def alternate_first_runs(before: Path, samples: int, repeat: int, model: bool) -> None:
    """First runs after ``compile`` of this checkout and ``before``, ``repeat`` fresh interpreters each, in turn.

    Each checkout gets a kernel cache of its own, filled once by ``valve-emulator compile`` (untimed); each child
    then imports, reads the CSV and diagnoses once (:data:`_FIRST_RUN_TIMED`), timed from outside (wall, and
    the child's CPU seconds) and from inside (the imports). Medians with their range, and the load average.
    The children run in a scratch folder: ``-c`` and ``-m`` put the working directory first on ``sys.path``,
    ahead of ``PYTHONPATH``, and a checkout's root would shadow the other."""
    roots = {"before": before.resolve(), "after": ROOT}
    runs: dict[str, list[dict]] = {k: [] for k in roots}
    with tempfile.TemporaryDirectory() as tmp:
        csv_path, model_path = _write_inputs(tmp, samples)
        envs = {label: {**os.environ, "PYTHONPATH": str(root), "NUMBA_CACHE_DIR": os.path.join(tmp, label)}
                for label, root in roots.items()}
        for env in envs.values():
            subprocess.run([sys.executable, "-m", "valve_emulator", "compile", "--only", "diagnose"], env=env,
                           check=True, capture_output=True, cwd=tmp)
        load_before = os.getloadavg()
        for _ in range(repeat):
            for label, env in envs.items():
                cpu0, wall0 = _children_cpu(), time.perf_counter()
                out = subprocess.run([sys.executable, "-c", _FIRST_RUN_TIMED, csv_path,
                                      model_path if model else "none"], env=env, check=True, capture_output=True,
                                     text=True, cwd=tmp).stdout
                run = {"wall": time.perf_counter() - wall0, "cpu": _children_cpu() - cpu0}
                runs[label].append({**run, **json.loads(out.splitlines()[-1])})
    for label, v in runs.items():
        parts = [f"{m} median {statistics.median(r[m] for r in v):5.2f} s "
                 f"({min(r[m] for r in v):.2f}–{max(r[m] for r in v):.2f})" for m in ("wall", "cpu", "import")]
        print(f"{samples:6d} samples, first run after `compile`, {label:6s}: {'; '.join(parts)}; "
              f"kernels compiled {max(r['compiled'] for r in v)}; answer {v[-1]['answer']}")
    print(f"load average (1, 5, 15 min) {', '.join(f'{x:.1f}' for x in load_before)} before the timed runs, "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} after")


def _children_cpu() -> float:
    """User + system CPU seconds of the finished children of this process."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def one_run(samples: int, model: bool) -> dict:
    """Warm up, then time one diagnosis of ``samples`` samples in this interpreter: wall and CPU seconds."""
    case = CASES[0]
    rec, nominal, _ = generate(case, duration=1000 + case.cut)
    explain(rec, nominal if model else None)
    rec, nominal, _ = generate(case, duration=samples - 1 + case.cut)
    wall, cpu = time.perf_counter(), time.process_time()
    d = explain(rec, nominal if model else None)
    out = {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu, "verdict": d.verdict}
    first = d.to_json()["findings"][:1]
    out["finding"] = [[f["physics"], f["parameters"], f.get("intervals")] for f in first]
    return out


def alternate(before: Path, samples: list[int], repeat: int, model: bool) -> None:
    """Each size ``repeat`` times, this checkout and ``before`` one after the other (see the module docstring)."""
    roots = {"before": before.resolve(), "after": ROOT}
    for n in samples:
        load_before = os.getloadavg()
        runs: dict[str, list[dict]] = {k: [] for k in roots}
        for _ in range(repeat):
            for label, root in roots.items():
                cmd = [sys.executable, str(ROOT / "bench" / "bench_diagnose.py"), "--one", str(n)]
                cmd += [] if model else ["--no-model"]
                out = subprocess.run(cmd, env={**os.environ, "PYTHONPATH": str(root)}, check=True,
                                     capture_output=True, text=True).stdout
                runs[label].append(json.loads(out.splitlines()[-1]))
        med = {k: {m: statistics.median(r[m] for r in v) for m in ("wall", "cpu")} for k, v in runs.items()}
        for label, v in runs.items():
            walls = ", ".join(f"{r['wall']:.2f}" for r in v)
            print(f"{n:6d} samples {label:6s}: wall median {med[label]['wall']:5.2f} s ({walls}), "
                  f"CPU median {med[label]['cpu']:5.2f} s | {v[-1]['verdict']}")
        print(f"{n:6d} samples after/before: wall {med['after']['wall'] / med['before']['wall']:.2f}, "
              f"CPU {med['after']['cpu'] / med['before']['cpu']:.2f}; load average (1, 5, 15 min) "
              f"{', '.join(f'{x:.1f}' for x in load_before)} before, "
              f"{', '.join(f'{x:.1f}' for x in os.getloadavg())} after")
        for label, v in runs.items():
            print(f"{n:6d} samples {label:6s} first finding: {v[-1]['finding']}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, nargs="+", default=[1000, 10000])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--no-model", action="store_true", help="identify the linear part from the data instead")
    p.add_argument("--no-first-run", action="store_true", help="skip the first-run (empty cache) timings")
    p.add_argument("--before", type=Path, help="another checkout, measured alternately with this one")
    p.add_argument("--first-runs", action="store_true",
                   help="with --before: time first runs after `compile` (fresh interpreters) instead of warm runs")
    p.add_argument("--one", type=int, help=argparse.SUPPRESS)   # a child of --before: one timed run, JSON
    args = p.parse_args(argv)
    if args.one is not None:
        print(json.dumps(one_run(args.one, not args.no_model)))
        return 0
    if args.before is not None:
        print(f"{os.cpu_count()} CPU(s); load {os.getloadavg()[0]:.1f}; "
              f"{'no model' if args.no_model else 'nominal model given'}")
        for n in args.samples if args.first_runs else []:
            alternate_first_runs(args.before, n, args.repeat, not args.no_model)
        if not args.first_runs:
            alternate(args.before, args.samples, args.repeat, not args.no_model)
        return 0
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
        first = "" if args.no_first_run else (f" | first run {first_run(n, not args.no_model):5.1f} s, after "
                                              f"`compile` {first_run(n, not args.no_model, ahead=True):5.1f} s")
        print(f"{len(rec):6d} samples: warm median {statistics.median(times):5.2f} s (min {min(times):.2f}, "
              f"max {max(times):.2f}){first} | {d.verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
