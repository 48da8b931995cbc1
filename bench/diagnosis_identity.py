"""Check that a change to the diagnosis leaves every answer identical: same documents before and after.

Diagnoses a fixed set of recordings — the proof cases (:data:`valve_emulator.benchmark.cases.CASES`) and
``--draws`` draws of each independent family in :data:`FAMILIES`, each with its nominal model and as plant data
(``op_range=(0, 100)``) — and keeps, per recording, two things:

* ``json``: the ``diagnose --json`` document (:meth:`~valve_emulator.diagnosis.report.diagnosis.Diagnosis.
  to_json`), what a user sees. It must be identical.
* ``exact``: full-precision numbers behind it — the held-out fits, every ranked option's ΔBIC and held-out fit,
  each finding's parameters and intervals, the fitted linear part and a digest of the final model's PV. A
  floating-point reordering shows up here first (a last digit), before it could reach ``json``.

Wall times are not compared (``seconds`` is not in either part). Run::

    python bench/diagnosis_identity.py --write /tmp/before.json          # on the reference checkout
    python bench/diagnosis_identity.py --compare /tmp/before.json        # on the changed one
    python bench/diagnosis_identity.py --before /path/to/reference/checkout   # both, the reference in a child
    python bench/diagnosis_identity.py --before CHECKOUT --draws 1 --long 10000 100000   # and the benchmark's sizes

Exit status 0 when every ``json`` document is identical (``exact`` differences are listed, not fatal unless
``--strict``), 1 otherwise.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: The independent families diagnosed (a sticky level loop, physics starting late, a healthy valve under an
#: aggressive PI, a sticky flow loop).
FAMILIES = ("level_sticky", "late_onset", "aggressive_pi", "flow_sticky")


def _digest(x) -> str:
    return hashlib.sha256(np.ascontiguousarray(np.asarray(x, dtype=float)).tobytes()).hexdigest()[:16]


def _exact(diagnosis) -> dict:
    """Full-precision numbers of a diagnosis (``repr`` of floats), for a comparison stricter than its JSON."""
    e = diagnosis.explanation
    if e is None:
        return {}
    return {
        "fits": [repr(e.fit_before), repr(e.fit_base), repr(e.fit_after)],
        "ranking": [[r.round, r.option, r.parameters, repr(r.delta_bic), repr(r.heldout), r.chosen]
                    for r in e.ranking],
        "findings": [[f.physics, repr(f.parameters), repr(f.intervals), repr(f.delta_bic), repr(f.fit_with),
                      repr(f.load_delta_bic)] for f in e.findings],
        "plant": repr(e.plant),
        "linear_tests": [repr(m) for m in e.linear_tests],
        "input_delta_bic": repr(e.input_delta_bic),
        "pv_after": _digest(e.traces.pv_after),
    }


def recordings(draws: int, long: tuple[int, ...] = ()):
    """(name, recording, nominal model or None, diagnose options): the fixed set, in a fixed order, then the
    benchmark's recording (``bench_diagnose.py``: the first proof case lengthened) at each size of ``long``
    with its model — the sizes where the kernels' threads and the windowed coarse stages come into play."""
    from valve_emulator.benchmark import independent
    from valve_emulator.benchmark.cases import CASES, generate
    from valve_emulator.config import loop_from_mapping

    for case in CASES:
        rec, nominal, _ = generate(case)
        yield f"case {case.name} | model", rec, nominal, {}
        yield f"case {case.name} | plant data", rec, None, {"op_range": (0, 100)}
    for family in FAMILIES:
        for i in range(draws):
            rec, _, nominal = independent.draw(family, np.random.default_rng([1, i]))
            yield f"{family} {i} | model", rec, loop_from_mapping(nominal), {}
            yield f"{family} {i} | plant data", rec, None, {"op_range": (0, 100)}
    for n in long:
        rec, nominal, _ = generate(CASES[0], duration=n - 1 + CASES[0].cut)
        yield f"case {CASES[0].name} {n} samples | model", rec, nominal, {}


def documents(draws: int, only: str | None = None, long: tuple[int, ...] = ()) -> dict:
    """name → {"json", "exact", "seconds"} for every recording of :func:`recordings`."""
    import valve_emulator as ve

    out = {}
    for name, rec, model, options in recordings(draws, long):
        if only and only not in name:
            continue
        t = time.perf_counter()
        d = ve.diagnose(rec, model, **options)
        seconds = time.perf_counter() - t
        out[name] = {"json": json.loads(json.dumps(d.to_json())), "exact": _exact(d), "seconds": seconds}
        print(f"{seconds:6.2f} s  {name}: {d.answer}", file=sys.stderr, flush=True)
    return out


def compare(before: dict, after: dict) -> tuple[list[str], list[str]]:
    """(names whose JSON differs, names whose exact numbers differ), with the first differing key."""
    json_diff, exact_diff = [], []
    for name in before:
        if name not in after:
            json_diff.append(f"{name}: missing")
            continue
        if before[name]["json"] != after[name]["json"]:
            json_diff.append(f"{name}: {_first_difference(before[name]['json'], after[name]['json'])}")
        if before[name]["exact"] != after[name]["exact"]:
            exact_diff.append(f"{name}: {_first_difference(before[name]['exact'], after[name]['exact'])}")
    return json_diff, exact_diff


def _first_difference(a, b, path: str = "") -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if a.get(k) != b.get(k):
                return _first_difference(a.get(k), b.get(k), f"{path}.{k}")
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            if x != y:
                return _first_difference(x, y, f"{path}[{i}]")
    return f"{path or '/'}: {a!r} → {b!r}"


def _times(docs: dict) -> float:
    return sum(d["seconds"] for d in docs.values())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", type=Path, help="write this checkout's documents to a JSON file")
    g.add_argument("--compare", type=Path, help="compare this checkout's documents with a written JSON file")
    g.add_argument("--before", type=Path, help="another checkout: write its documents in a child, then compare")
    p.add_argument("--draws", type=int, default=3, help="draws per independent family")
    p.add_argument("--only", help="only the recordings whose name contains this text")
    p.add_argument("--long", type=int, nargs="*", default=[],
                   help="also the benchmark's recording at these sizes (samples), with its model")
    p.add_argument("--strict", action="store_true", help="fail on full-precision differences too")
    args = p.parse_args(argv)
    if args.before is not None:
        with tempfile.TemporaryDirectory() as tmp:
            ref = Path(tmp) / "before.json"
            cmd = [sys.executable, __file__, "--write", str(ref), "--draws", str(args.draws)]
            cmd += ["--only", args.only] if args.only else []
            cmd += ["--long", *map(str, args.long)] if args.long else []
            subprocess.run(cmd, env={**os.environ, "PYTHONPATH": str(args.before.resolve())}, check=True)
            before = json.loads(ref.read_text())
    elif args.compare is not None:
        before = json.loads(args.compare.read_text())
    else:
        before = None
    after = documents(args.draws, args.only, tuple(args.long))
    if before is None:
        args.write.write_text(json.dumps(after, indent=1))
        print(f"{len(after)} documents written to {args.write} ({_times(after):.1f} s of diagnosis)")
        return 0
    if args.only:
        before = {k: v for k, v in before.items() if args.only in k}
    json_diff, exact_diff = compare(before, after)
    print(f"{len(before)} recordings; diagnosis time {_times(before):.1f} s before, {_times(after):.1f} s after")
    for line in json_diff:
        print(f"JSON DIFFERS  {line}")
    for line in exact_diff:
        print(f"exact differs {line}")
    print("identical documents" if not json_diff else f"{len(json_diff)} documents differ",
          f"({len(exact_diff)} with full-precision differences)")
    return 1 if json_diff or (args.strict and exact_diff) else 0


if __name__ == "__main__":
    sys.exit(main())
