"""Check that a change to the independent simulator leaves every recording bit for bit, and time it.

Every loop the property tests diagnose (the distinct ``(family, entropy)`` of ``tests/unseen_loops.ALL``) is
drawn by this checkout's :mod:`valve_emulator.benchmark.independent` and, with ``--before``, by another
checkout's copy of that module (loaded from its file, both in this process, one loop after the other in turns).
Per loop a SHA-256 of each recorded array (t, SP, OP, PV), of the truth's stem travel and load series, and of
the rest of the truth and the nominal mapping as JSON; ``--edges`` adds loops outside the families' draws
(dead times of 0, ½, 1 and 3.3 substeps, an equal-percentage valve, an actuator lag in either order, 7 substeps,
an SP of its own, a quantised PV, an open loop) with the stem travel recorded. The shared documents of a test
run are diagnoses of these recordings: one bit changed would change what every test reads. Run::

    python bench/independent_identity.py --before /path/to/reference/checkout [--edges] [--every 1]

It prints the number of loops identical and each side's CPU seconds per loop (median and total: the draw's
process CPU); exit status 0 when every loop is identical, 1 otherwise.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path
from types import ModuleType

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODULE = Path("valve_emulator") / "benchmark" / "independent.py"


def _module(path: Path, name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module   # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)
    return module


def _sha(value) -> str:
    if isinstance(value, np.ndarray):
        return hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=repr).encode()).hexdigest()


def _draw_digest(module: ModuleType, family: str, entropy: tuple[int, ...]) -> tuple[dict, float]:
    start = time.process_time()
    rec, truth, nominal = module.draw(family, np.random.default_rng(list(entropy)))
    cpu = time.process_time() - start
    rest = {k: v for k, v in truth.items() if k not in ("mv", "load_series")}
    return ({f: _sha(getattr(rec, f)) for f in ("t", "sp", "op", "pv")} | {
        "mv": _sha(truth["mv"]), "load": _sha(truth["load_series"]), "truth": _sha(rest),
        "nominal": _sha(nominal), "source": rec.source}, cpu)


def _edge_loops(module: ModuleType) -> list[tuple[str, object]]:
    """Loops outside the families' draws, built with ``module``'s records (two drawn loops of each family,
    each changed in one part at a time), and an open loop per family on the last one's OP."""
    out = []
    for family in module.FAMILIES:
        for s in range(2):
            base, _ = module.draw_loop(family, np.random.default_rng([99, s, len(out)]))
            h = base.dt / base.substeps
            changes = {"as drawn": {}, "no dead time": {"plant": replace(base.plant, delay=0.0)}}
            for substeps in (0.5, 1.0, 1.0000001, 3.3):
                changes[f"dead time {substeps} substeps"] = {"plant": replace(base.plant, delay=h * substeps)}
            changes |= {
                "equal percentage": {"valve": replace(base.valve, characteristic="equal_percentage",
                                                      rangeability=30.0)},
                "friction, then a lag": {"valve": replace(base.valve, order="friction_first", actuator_lag=2.0)},
                "a lag, then friction": {"valve": replace(base.valve, order="lag_first", actuator_lag=0.7)},
                "7 substeps": {"substeps": 7}, "its own SP": {"sp0": 47.0},
                "quantised": {"measurement": replace(base.measurement, quantum=0.3)}, "short": {"duration": 200.0}}
            out.extend((f"{family}/{s}/{label}", replace(base, **change)) for label, change in changes.items())
        closed, _ = module.simulate(out[-1][1])
        op = closed.op + 3.0 * np.sin(np.arange(closed.op.size) / 7.0)
        out.append((f"{family}/open loop", replace(out[-1][1], manual_op=tuple(op))))
    return out


def _edge_digest(module: ModuleType, loop) -> dict:
    rec, truth = module.simulate(loop, record_mv=True)
    return {f: _sha(getattr(rec, f)) for f in ("t", "sp", "op", "pv", "mv")} | {
        "mv": _sha(truth["mv"]), "load": _sha(truth["load_series"])}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="the reference checkout")
    parser.add_argument("--every", type=int, default=1, help="every k-th loop of ALL only (default all)")
    parser.add_argument("--edges", action="store_true", help="also the loops outside the families' draws")
    args = parser.parse_args(argv)
    sys.path.insert(0, str(ROOT / "tests"))
    import unseen_loops

    after = _module(ROOT / MODULE, "independent_after")
    before = _module(args.before / MODULE, "independent_before")
    loops = list(dict.fromkeys((d.family, d.entropy) for d in unseen_loops.ALL))[::args.every]
    cpu: dict[str, list[float]] = {"before": [], "after": []}
    differ = []
    for n, (family, entropy) in enumerate(loops):
        sides = [("before", before), ("after", after)]
        digests = {}
        for side, module in sides if n % 2 == 0 else sides[::-1]:   # in turns: neither side always first
            digests[side], seconds = _draw_digest(module, family, entropy)
            cpu[side].append(seconds)
        if digests["before"] != digests["after"]:
            differ.append(f"{family}-{'.'.join(map(str, entropy))}")
    print(f"{len(loops) - len(differ)} of {len(loops)} loops of tests/unseen_loops.ALL identical, bit for bit")
    for side in ("before", "after"):
        print(f"  {side}: CPU per draw median {statistics.median(cpu[side]):.3f} s, total {sum(cpu[side]):.1f} s")
    ratios = [b / a for b, a in zip(cpu["before"], cpu["after"])]
    print(f"  before / after per loop: median {statistics.median(ratios):.2f} "
          f"(quartiles {np.percentile(ratios, 25):.2f}-{np.percentile(ratios, 75):.2f})")
    if args.edges:
        edges = _edge_loops(before)
        edges_differ = [name for name, loop in edges if _edge_digest(before, loop) != _edge_digest(after, loop)]
        print(f"{len(edges) - len(edges_differ)} of {len(edges)} edge loops identical, bit for bit")
        differ += edges_differ
    for name in differ:
        print("differs:", name)
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
