r"""Candidate ``dead_time``: the plant's dead time θ differs from the nominal one.

The dead time is part of the linear fit, which searches it on an integer-sample grid for every candidate
(a dead time wrong by one or two samples leaves S right but biases J 30–50 % low, so it must be
searched *with* the valve parameters). This candidate therefore transforms nothing; choosing it frees θ
(one more parameter for BIC), and :func:`~valve_emulator.diagnosis.fit.linear.polish` refines it to a
fraction of a sample.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainContext, DelayCandidate, register

__all__ = ["DeadTime"]


class DeadTime(DelayCandidate):
    name: ClassVar[str] = "dead_time"
    slot: ClassVar[str] = "delay"
    param_names: ClassVar[tuple[str, ...]] = ("theta",)
    n_params: ClassVar[int] = 1
    cause_rank: ClassVar[int | None] = 60

    def grid(self, ctx: ChainContext) -> np.ndarray:
        return np.array([[ctx.delay]])

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        return best[None, :]


    def parameters(self, p: np.ndarray) -> dict:
        return {"theta": round(float(p[0]), 3)}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        extra = f" (nominal {nominal['theta']:.3g} s)" if nominal and "theta" in nominal else ""
        return f"a dead-time error: θ ≈ {p[0]:.1f} s{extra}"


register(DeadTime())
