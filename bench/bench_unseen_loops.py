"""Benchmark: the diagnosis on recordings the search did not make.

Every loop comes from :mod:`valve_emulator.benchmark.independent`, a simulator that shares no code with the
searched model (continuous plants, a friction model written from its definition or a Karnopp force balance,
a PI one sample late). For each family, ``--draws`` loops are drawn and diagnosed twice: with the nominal
model the family hands out (the linear part and the tuning, an ideal valve) and as plant data (no model; OP is
declared to be % travel, ``op_range=(0, 100)``, as the standard recording format declares it). Run::

    python bench/bench_unseen_loops.py [--draws 8] [--seed 0] [--jobs 2] [--families a,b] [--json OUT]

Columns, per family and mode:

* ``correct``: the answer is the expected one (``stiction`` where the valve has S >= 1 % travel, else
  ``no_stiction``; ``cannot_tell`` and ``no_response`` are never correct); for ``aggressive_pi`` the answer
  must also name the tuning (reason or finding ``tuning``). ``tuning`` gives that rate alone.
* ``wrong``: the opposite call about the valve (``stiction`` on a valve expected ``no_stiction``, or
  ``no_stiction`` on a sticky one). ``correct`` and ``wrong`` need not add up to the draws: ``cannot_tell``
  (both explanations named) and ``no_response`` are neither right nor a wrong call — a hedge an engineer can act
  on by testing the valve, where a wrong call sends them the wrong way.
* ``S err``, ``J err``: median relative error of the friction estimate (in % travel) where friction was
  found on a loop that has it (J only where the true J >= 0.5 %).
* ``S cov``, ``J cov``: how often the reported 95 % interval contains the true value (same loops).
* ``edge``: findings (of any physics) that report a parameter on an end of the range the search explored as a
  value, which the diagnosis must not do (an estimate there is a bound, "R ≥ 368.9", with an interval open on
  that side): the ends are the candidate's declared ones
  (:meth:`~valve_emulator.diagnosis.candidates.base.Candidate.bounds`, for the recording's sample time and
  the identified plant's slowest time constant), and a parameter counts when its estimate lies within 0.1 %
  of one while its reported 95 % interval is closed on both sides. ``k/n``: k such findings of n.
* ``strong ok``: how often a stiction answer marked ``strong`` is right (the strength's calibration).
* ``disagree``: the answer and the findings disagree (an answer other than stiction with a friction finding
  or friction estimate, or a stiction answer without one).
* ``s/diag``: median wall seconds per diagnosis, after one untimed warm-up per process.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from valve_emulator.benchmark.independent import FAMILIES, draw

FRICTION = ("stiction", "deadband")
MIN_J = 0.5        # % travel: below it J's relative error says nothing
MODES = ("model", "plant")
CALLS = ("stiction", "no_stiction")   # the answers that call the valve one way or the other


def _warm_up() -> None:
    """Load (or compile) the diagnosis' kernels in this process, untimed, with one thread per process."""
    import numba

    import valve_emulator as ve
    from valve_emulator.config import loop_from_mapping

    numba.set_num_threads(1)
    rec, _, nominal = draw("flow_sticky", np.random.default_rng(12345))
    ve.diagnose(rec, loop_from_mapping(nominal))
    ve.diagnose(rec, op_range=(0.0, 100.0))


def _names_tuning(doc: dict) -> bool:
    return any(r["code"] == "tuning" for r in doc["reasons"]) or any(
        f["physics"] == "tuning" for f in doc.get("findings") or ())


def _search_ends(physics: str, rec, plant: dict) -> dict:
    """The declared ends of ``physics``'s search range, per parameter, for this recording and identified plant."""
    from valve_emulator.diagnosis.candidates import get
    from valve_emulator.diagnosis.candidates.base import ChainContext
    from valve_emulator.diagnosis.fit.frame import robust_range

    lo, hi = robust_range(rec.op)
    taus = plant.get("taus") or ()
    ctx = ChainContext(dt=rec.dt, op=rec.op, op_span=hi - lo, tau_plant=max(taus, default=10.0 * rec.dt))
    return get(physics).bounds(ctx)


def _at_edge_as_value(finding, rec, plant: dict) -> bool:
    """Whether ``finding`` reports a parameter on an end of its search range as a value (see the docstring)."""
    for name, ends in _search_ends(finding.physics, rec, plant).items():
        value = finding.parameters.get(name)
        if not isinstance(value, float):
            continue
        lo, hi = finding.intervals.get(name, (value, value))
        closed = all(x is not None and np.isfinite(x) for x in (lo, hi))
        if closed and any(end is not None and abs(value - end) <= 1e-3 * abs(end) for end in ends):
            return True
    return False


def edges(diagnosis) -> tuple[int, int]:
    """``(k, n)``: of the ``n`` findings of ``diagnosis``, the ``k`` that report a search edge as a value."""
    found = diagnosis.findings
    plant = {} if diagnosis.explanation is None else diagnosis.explanation.plant
    return sum(_at_edge_as_value(f, diagnosis.recording, plant) for f in found), len(found)


def score(doc: dict, truth: dict) -> dict:
    """One diagnosis against the truth: the row the table sums."""
    answer, friction = doc["answer"], doc["friction"]
    tuning = _names_tuning(doc)
    correct = answer == truth["expected"] and (tuning or not truth["tuning"])
    wrong = answer in CALLS and answer != truth["expected"]
    has_friction = friction is not None or any(f["physics"] in FRICTION for f in doc.get("findings") or ())
    row = {"answer": answer, "correct": correct, "wrong": wrong, "tuning": tuning, "strength": doc.get("strength"),
           "disagree": (answer == "stiction") != has_friction, "reasons": [r["code"] for r in doc["reasons"]],
           "findings": [f["physics"] for f in doc.get("findings") or ()]}
    if friction is not None and friction["travel"] is not None:
        travel = friction["travel"]
        row["S"], row["J"] = travel["S"]["value"], travel["J"]["value"]
        if truth["S"] > 0:
            S_lo, S_hi = travel["S"]["interval"]
            row["S_err"] = abs(row["S"] - truth["S"]) / truth["S"]
            row["S_cov"] = S_lo <= truth["S"] <= S_hi
            if truth["J"] >= MIN_J:
                J_lo, J_hi = travel["J"]["interval"]
                row["J_err"] = abs(row["J"] - truth["J"]) / truth["J"]
                row["J_cov"] = J_lo <= truth["J"] <= J_hi
    return row


def run_draw(family: str, index: int, seed: int) -> list[dict]:
    """Draw loop ``index`` of ``family`` and diagnose it both ways."""
    import valve_emulator as ve
    from valve_emulator.config import loop_from_mapping

    rec, truth, nominal = draw(family, np.random.default_rng([seed, list(FAMILIES).index(family), index]))
    rows = []
    for mode in MODES:
        t0 = time.perf_counter()
        d = (ve.diagnose(rec, loop_from_mapping(nominal)) if mode == "model" else
             ve.diagnose(rec, op_range=(0.0, 100.0)))
        seconds = time.perf_counter() - t0
        truth_brief = {k: truth[k] for k in ("expected", "tuning", "S", "J")}
        at_edge, found = edges(d)
        rows.append({"family": family, "index": index, "mode": mode, "seconds": seconds, "truth": truth_brief,
                     "valve": truth["valve"], "plant": truth["plant"], "margins": truth.get("margins"),
                     "edge": at_edge, "found": found, **score(d.to_json(), truth)})
    return rows


def _rate(rows: list[dict], key: str) -> str:
    values = [r[key] for r in rows if key in r]
    return f"{sum(values)}/{len(values)}" if values else "–"


def _sum(rows: list[dict], key: str, of: str) -> str:
    """``"k/n"``: ``key`` summed over the rows, of ``of`` summed."""
    return f"{sum(r.get(key, 0) for r in rows)}/{sum(r.get(of, 0) for r in rows)}"


def _median(rows: list[dict], key: str, fmt: str = "{:.0%}") -> str:
    values = [r[key] for r in rows if key in r]
    return fmt.format(statistics.median(values)) if values else "–"


def _row(label: str, mode: str, sel: list[dict]) -> tuple:
    return (label, mode, len(sel), _rate(sel, "correct"), _rate(sel, "wrong"),
            _rate([r for r in sel if r["family"] == "aggressive_pi"], "tuning"),
            _median(sel, "S_err"), _median(sel, "J_err"), _rate(sel, "S_cov"), _rate(sel, "J_cov"),
            _sum(sel, "edge", "found"), _rate([r for r in sel if r["strength"] == "strong"], "correct"),
            _rate(sel, "disagree"), _median(sel, "seconds", "{:.1f}"),
            " ".join(f"{a}:{n}" for a, n in sorted(_count(r["answer"] for r in sel).items())))


def summary(rows: list[dict]) -> list[tuple]:
    """A row per family and mode, then one over every row (``all``)."""
    out = [_row(family, mode, sel) for family in FAMILIES for mode in MODES
           if (sel := [r for r in rows if r["family"] == family and r["mode"] == mode])]
    return out + [_row("all", "both", rows)] if rows else out


def _count(items) -> dict:
    counts: dict = {}
    for x in items:
        counts[x] = counts.get(x, 0) + 1
    return counts


HEADER = ("family", "mode", "draws", "correct", "wrong", "tuning", "S err", "J err", "S cov", "J cov", "edge",
          "strong ok", "disagree", "s/diag", "answers")


def table(rows: list[tuple]) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "|".join("---" for _ in HEADER) + "|"]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=8, help="loops per family (default 8)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2, help="processes (default 2)")
    parser.add_argument("--families", default=",".join(FAMILIES), help="comma-separated (default: all)")
    parser.add_argument("--json", metavar="OUT", help="write every row and the table as JSON")
    args = parser.parse_args(argv)
    families = [f for f in args.families.split(",") if f]
    unknown = [f for f in families if f not in FAMILIES]
    if unknown:
        parser.error(f"--families: unknown {', '.join(unknown)}; known: {', '.join(FAMILIES)}")
    tasks = [(f, i, args.seed) for f in families for i in range(args.draws)]
    rows: list[dict] = []
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs, initializer=_warm_up) as pool:
        for done, result in enumerate(pool.map(run_draw, *zip(*tasks)), 1):
            rows += result
            print(f"\r{done}/{len(tasks)} loops, {time.perf_counter() - t0:.0f} s", end="", file=sys.stderr,
                  flush=True)
    print(file=sys.stderr)
    summary_rows = summary(rows)
    print(table(summary_rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"draws": args.draws, "seed": args.seed, "table": [dict(zip(HEADER, r)) for r in summary_rows],
                       "rows": rows}, f, indent=1, default=float)
        print(f"wrote {os.path.abspath(args.json)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
