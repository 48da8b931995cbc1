"""A valve that holds OP's moves inside a band, written for the tests independently of the package's physics."""

from __future__ import annotations

import numpy as np


def held(op: np.ndarray, width: float) -> np.ndarray:
    """The travel of a valve that holds until OP has moved ``width / 2`` beyond it either way (a play operator:
    a dead band of total width ``width``), starting at OP's first value."""
    out = np.empty_like(op)
    x = op[0]
    for k, u in enumerate(op):
        x = min(max(x, u - width / 2), u + width / 2)
        out[k] = x
    return out


def level_through_band(seed: int, healthy: bool, S: float = 3.0, n: int = 2000, dt: float = 1.0,
                       noise: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A level loop's record through a valve that is healthy or holds OP's moves inside a dead band ``S``: OP
    wandering over about ten times the band with small fast moves on top, the band's output (:func:`held`), and the
    level PV — the integral of the valve's flow (healthy: OP itself) delayed 2 samples, plus a random-walk load and
    measurement noise of σ ``noise``."""
    rng = np.random.default_rng(seed)
    op = 50 + np.cumsum(rng.normal(0, 0.4, n)) + rng.normal(0, 0.5, n)
    claimed = held(op, S)
    flow = op if healthy else claimed
    load = np.cumsum(rng.normal(0, 0.01, n))
    pv = np.cumsum(0.03 * dt * np.concatenate([np.full(3, flow[0]), flow[:-3]])) + np.cumsum(load) * 0.01
    return pv + rng.normal(0, noise, n), op, claimed
