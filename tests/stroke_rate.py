"""A new candidate physics written as one file, as a user would add one, and a recording of its physics.

The toy is a valve whose stem strokes at a limited rate (a slow positioner): MV follows OP at most ``rate`` %
per second. It sits in the valve slot and declares no twin role, since the loop config has no key for it. It is
not registered here: each test registers it for itself (and the library is restored afterwards).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from valve_emulator.config import loop_from_mapping
from valve_emulator.diagnosis.candidates import ChainCandidate, ChainContext
from valve_emulator.recordings.recording import Recording

TOY = "stroke_rate"
RATE, GAIN, TAU, DELAY = 0.4, 2.0, 8.0, 3.0


def rate_limited(op: np.ndarray, rate: np.ndarray, dt: float) -> np.ndarray:
    """``op`` (T,) or (T, n) followed at most ``rate`` (n,) per second, from ``op[0]``: (T, n)."""
    x = np.asarray(op, dtype=float)
    x = np.repeat(x[:, None], rate.size, axis=1) if x.ndim == 1 else x
    out = np.empty_like(x)
    out[0] = x[0]
    for k in range(1, x.shape[0]):
        out[k] = out[k - 1] + np.clip(x[k] - out[k - 1], -rate * dt, rate * dt)
    return out


class StrokeRate(ChainCandidate):
    """The whole of a new candidate: where it acts, its parameters and grids, its transform and its words."""

    name: ClassVar[str] = TOY
    slot: ClassVar[str] = "valve"
    param_names: ClassVar[tuple[str, ...]] = ("rate",)
    n_params: ClassVar[int] = 1
    dims: ClassVar[dict[str, str]] = {"rate": "op"}       # % per second scales like an OP difference
    cause_rank: ClassVar[int | None] = 35

    def grid(self, ctx: ChainContext) -> np.ndarray:
        return np.geomspace(ctx.op_span / 2000.0, ctx.op_span / 2.0, 30)[:, None] / ctx.dt

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        return np.vstack([best[None, :], best[0] * np.exp(np.linspace(-0.3, 0.3, 13))[:, None]])

    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        return rate_limited(x, params[:, 0], ctx.dt)

    def parameters(self, p: np.ndarray) -> dict:
        return {"rate": round(float(p[0]), 4)}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        return f"a valve stroking at most {p[0]:.3g}{units} per second"


def slow_valve() -> tuple[Recording, object]:
    """OP steps through a slow valve into a first-order plant with dead time, and the model without the limit."""
    rng = np.random.default_rng(4)
    dt, T, d = 1.0, 1500, int(DELAY)
    op = np.repeat(rng.uniform(30.0, 70.0, T // 75), 75) + rng.normal(0.0, 0.05, T)
    mv = rate_limited(op, np.array([RATE]), dt)[:, 0]
    a = np.exp(-dt / TAU)
    pv = np.zeros(T)
    for k in range(T - 1):
        pv[k + 1] = a * pv[k] + GAIN * (1.0 - a) * (mv[k - d] if k >= d else mv[0])
    pv += rng.normal(0.0, 0.05, T)
    t = np.arange(T) * dt
    model = loop_from_mapping({"name": "slow_valve", "valve": {"S": 0.0, "J": 0.0},
                               "plant": {"num": [GAIN], "den": [TAU, 1.0], "delay": DELAY, "pv0": 0.0},
                               "controller": {"kc": 0.3, "ti": 10.0, "sp": 100.0, "bias": 50.0}})
    return Recording(t, None, op, None, pv, source="slow_valve.csv"), model
