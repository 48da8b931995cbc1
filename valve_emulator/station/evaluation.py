"""Trainee performance evaluation: IAE and time outside limits per loop, response times, the action log.

Per loop ``i`` over the ticks of a session (sample ``k`` at simulated time ``t_k``, tick ``Δt``):

.. math:: \\mathrm{IAE}_i = \\sum_k |sp_{i,k} - pv_{i,k}|\\,\\Delta t, \\qquad
          T^{out}_i = \\sum_k \\Delta t\\,[pv_{i,k} < lo_i \\lor pv_{i,k} > hi_i],

the rectangle rule on the device's own samples -- what a recording of the session holds, so the figure can
be recomputed from the recording (``docs/station.md``). Both are accumulated with one vectorised update per
tick for the whole fleet.

*Time to the first correct action*: for every malfunction the instructor injects, the simulated time from
the injection to the trainee's first action on that loop that the malfunction calls for
(:data:`CORRECT_ACTIONS`: a sticking or seized valve and a failed transmitter call for manual mode, a load
change for any move of OP, SP or mode). Published OTS scoring (SimuPACT, Simtronics) scores exactly these:
variables against limits over time, and time to detect and act.

A trend of the first :data:`TREND_LOOPS` loops is kept in a ring (the report's PNGs, the pages' history).
"""

from __future__ import annotations

import io
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from valve_emulator.device.malfunctions import Kind

__all__ = ["Action", "Evaluation", "CORRECT_ACTIONS", "TREND_LOOPS", "Trend"]

#: malfunction kind -> the trainee actions that count as a correct response (kinds without one are not timed)
CORRECT_ACTIONS: dict[Kind, frozenset[str]] = {
    Kind.STICTION: frozenset({"manual"}),
    Kind.SEIZE: frozenset({"manual"}),
    Kind.SENSOR_STUCK: frozenset({"manual"}),
    Kind.SENSOR_DRIFT: frozenset({"manual"}),
    Kind.LOAD: frozenset({"manual", "auto", "op", "sp"}),
    Kind.NOISE: frozenset({"manual", "ack"}),
}
TREND_LOOPS = 16


@dataclass(kw_only=True)
class Action:
    """One trainee (or instructor) action: what, on which unit, when (simulated and wall time)."""

    who: str            # "trainee" or "instructor"
    unit: int | None
    action: str         # manual, auto, sp, op, ack, malfunction, hint, snapshot, ...
    value: Any = None
    sim_time: float
    wall_time: float = field(default_factory=time.time)
    accepted: bool = True
    message: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class Trend:
    """The last ``size`` samples of ``t, sp, pv, op, mv`` for the first ``loops`` loops (a ring)."""

    CHANNELS = ("sp", "pv", "op", "mv")

    def __init__(self, loops: int, size: int = 6000) -> None:
        self.loops, self.size = loops, size
        self.t = np.zeros(size)
        self.data = np.zeros((len(self.CHANNELS), size, loops))
        self.count = 0

    def add(self, t: float, sp: np.ndarray, pv: np.ndarray, op: np.ndarray, mv: np.ndarray) -> None:
        j = self.count % self.size
        self.t[j] = t
        for c, x in enumerate((sp, pv, op, mv)):
            self.data[c, j] = x[: self.loops]
        self.count += 1

    def series(self, index: int) -> dict[str, np.ndarray]:
        n = min(self.count, self.size)
        order = np.arange(self.count - n, self.count) % self.size
        out = {"t": self.t[order]}
        out.update({name: self.data[c, order, index] for c, name in enumerate(self.CHANNELS)})
        return out

    def clear(self) -> None:
        self.count = 0


class Evaluation:
    """Scores of one training session for ``n`` loops with alarm limits ``lo``, ``hi`` (PV units)."""

    def __init__(self, *, n: int, dt: float, lo: np.ndarray, hi: np.ndarray, units: list[int]) -> None:
        self.n, self.dt, self.units = n, float(dt), units
        self.lo, self.hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        self.trend = Trend(min(n, TREND_LOOPS))
        self.reset(0.0)

    def reset(self, t: float) -> None:
        """Start a new session at simulated time ``t``."""
        self.start = t
        self.samples = 0
        self.iae = np.zeros(self.n)
        self.outside = np.zeros(self.n)
        self.actions: list[Action] = []
        self.pending: list[tuple[float, int, str]] = []   # (t injected, unit, kind) still awaiting an action
        self.responses: list[dict[str, Any]] = []
        self.trend.clear()
        self.hints_released: list[str] = []
        self.wall_start = time.time()

    def add_sample(self, t: float, sp: np.ndarray, pv: np.ndarray, op: np.ndarray, mv: np.ndarray) -> None:
        """One tick's samples of every loop."""
        self.iae += np.abs(sp - pv) * self.dt
        self.outside += ((pv < self.lo) | (pv > self.hi)) * self.dt
        self.samples += 1
        self.trend.add(t, sp, pv, op, mv)

    def malfunction(self, t: float, unit: int, kind: str) -> None:
        if kind in CORRECT_ACTIONS:
            self.pending.append((t, unit, kind))

    def action(self, act: Action) -> None:
        """Log ``act``; a trainee's accepted action answers the malfunctions on its loop that call for it."""
        self.actions.append(act)
        if act.who != "trainee" or not act.accepted:
            return
        still = []
        for t_m, unit, kind in self.pending:
            if unit == act.unit and act.action in CORRECT_ACTIONS[kind]:
                self.responses.append({"unit": unit, "malfunction": kind, "injected": t_m, "action": act.action,
                                       "at": act.sim_time, "response_time": act.sim_time - t_m})
            else:
                still.append((t_m, unit, kind))
        self.pending = still

    def report(self, now: float, *, names: list[str], score_rules: dict[str, float] | None = None,
               expert: dict[str, Any] | None = None) -> dict[str, Any]:
        """The session report (JSON-able); ``expert`` is the report of an expert run of the same scenario."""
        rules = {"iae": 1.0, "outside": 1.0, "response": 1.0, "hint": 10.0, **(score_rules or {})}
        loops = []
        for i in range(self.n):
            loops.append({"unit": self.units[i], "name": names[i], "iae": float(self.iae[i]),
                          "time_outside": float(self.outside[i]), "limits": [float(self.lo[i]), float(self.hi[i])]})
        unanswered = [{"unit": u, "malfunction": k, "injected": t, "waiting": now - t} for t, u, k in self.pending]
        penalty = (rules["iae"] * float(self.iae.sum()) + rules["outside"] * float(self.outside.sum())
                   + rules["response"] * sum(r["response_time"] for r in self.responses)
                   + rules["response"] * sum(u["waiting"] for u in unanswered)
                   + rules["hint"] * len(self.hints_released))
        report = {"start": self.start, "end": now, "duration": now - self.start, "samples": self.samples,
                  "dt": self.dt, "loops": loops, "responses": self.responses, "unanswered": unanswered,
                  "hints_released": list(self.hints_released),
                  "actions": [a.as_dict() for a in self.actions],
                  "score": {"penalty": penalty, "rules": rules, "score": 100.0 / (1.0 + penalty / 100.0)}}
        if expert is not None:
            report["expert"] = _compare(report, expert)
        return report


def _compare(report: dict[str, Any], expert: dict[str, Any]) -> dict[str, Any]:
    """Trainee minus expert, per loop (IAE, time outside) and for the score."""
    by_unit = {lp["unit"]: lp for lp in expert.get("loops", [])}
    loops = [{"unit": lp["unit"], "iae_vs_expert": lp["iae"] - by_unit[lp["unit"]]["iae"],
              "time_outside_vs_expert": lp["time_outside"] - by_unit[lp["unit"]]["time_outside"]}
             for lp in report["loops"] if lp["unit"] in by_unit]
    return {"loops": loops, "score_vs_expert": report["score"]["score"] - expert["score"]["score"]}


def trend_png(series: dict[str, np.ndarray], *, title: str, show_mv: bool) -> bytes:
    """A PNG of PV and SP (top) and OP (and MV) (bottom) against simulated time."""
    from matplotlib.figure import Figure  # a figure of its own: no pyplot state, the process' backend untouched

    fig = Figure(figsize=(7, 3.6), dpi=90)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    t = series["t"]
    ax1.plot(t, series["pv"], label="PV", color="#1f6fb4")
    ax1.plot(t, series["sp"], label="SP", color="#2a9d3a", linestyle="--")
    ax2.plot(t, series["op"], label="OP", color="#d0612a")
    if show_mv:
        ax2.plot(t, series["mv"], label="MV", color="#7a4bb0")
    ax1.set_title(title)
    ax1.legend(loc="upper right", fontsize=8)
    ax2.legend(loc="upper right", fontsize=8)
    ax2.set_xlabel("simulated time (s)")
    ax2.set_ylabel("%")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def finite(x: float) -> float | None:
    """``x``, or ``None`` where JSON has no number for it."""
    return x if math.isfinite(x) else None
