r"""Candidate ``saturation``: the flow stops following the valve beyond a limit inside 0–100 %.

A valve that reaches a travel stop early (a positioner range set short, a mechanical limit), or a flow that
hits a hydraulic limit (a pump at its maximum, a line at choked flow), passes no more flow however far OP
goes on; the controller then winds up, so OP ramps while PV stays put — which also looks like a stuck
valve. The model clips the chain signal after the characteristic,

.. math::  \text{flow} = \min(\max(x, \ell), h),

with one active limit (``lo`` = ℓ or ``hi`` = h; the other one at the travel stop, 0 or 100 %), so one
parameter for BIC. On plant data it is a candidate only where OP's travel span is known or OP demonstrably sits
flat at an extreme (:func:`op_flat_at_extreme`). Its signature: the residual of a model without it lives where
OP sits beyond the limit.

Limits are levels on the travel scale (0 and 100 % at the travel stops,
:meth:`~valve_emulator.diagnosis.candidates.base.ChainContext.travel`). Grid: each side at the 2nd … 40th
percentiles of OP (``lo``) and the 60th … 98th (``hi``), so that at least 2 % of the samples lie beyond the
limit (fewer could not be told from noise); :meth:`refine` searches ±1.5 grid steps around the best at a tenth
of a step.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainCandidate, ChainContext, TwinRole, register

__all__ = ["Saturation", "PERCENTILES", "op_flat_at_extreme", "FLAT_EXTREME_SHARE", "FLAT_EXTREME_MIN"]

#: Percentiles of OP tried as a lower limit (and 100 − p as an upper one).
PERCENTILES = (2.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0)
#: OP "flat at an extreme": one unbroken run of at least this share of the record (and
#: :data:`FLAT_EXTREME_MIN` samples) exactly at OP's highest or lowest value — a controller output held at
#: its limit repeats one value, where a moving or noisy OP touches its extreme for a sample or two.
FLAT_EXTREME_SHARE = 0.05
FLAT_EXTREME_MIN = 10


def op_flat_at_extreme(op: np.ndarray) -> bool:
    """Whether OP sits flat at its highest or lowest value for one run of :data:`FLAT_EXTREME_SHARE` of the
    record (at least :data:`FLAT_EXTREME_MIN` samples): there OP is at a limit, so a flow limit (saturation)
    can be told from the data even when the travel span is not known. Independent of OP's units."""
    op = np.asarray(op, dtype=float)
    span = float(np.ptp(op)) if op.size else 0.0
    if not span > 0.0:
        return False
    need = max(FLAT_EXTREME_MIN, int(np.ceil(FLAT_EXTREME_SHARE * op.size)))
    tol = 1e-9 * span  # the same value, up to the rounding of a unit conversion
    for at in (op >= op.max() - tol, op <= op.min() + tol):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], at.astype(np.int8), [0]])))
        if edges.size and int(np.max(edges[1::2] - edges[::2])) >= need:
            return True
    return False


class Saturation(ChainCandidate):
    name: ClassVar[str] = "saturation"
    slot: ClassVar[str] = "limit"
    param_names: ClassVar[tuple[str, ...]] = ("lo", "hi")
    n_params: ClassVar[int] = 1
    dims: ClassVar[dict[str, str]] = {"lo": "op_level", "hi": "op_level"}
    cause_rank: ClassVar[int | None] = 30
    needs_span: ClassVar[bool] = True   # limits are travel levels
    twin_role: ClassVar[TwinRole | None] = TwinRole.FLOW_LIMITS

    def shows_without_span(self, op: np.ndarray) -> bool:
        """OP held flat at an extreme (:func:`op_flat_at_extreme`) is a limit the data place themselves."""
        return op_flat_at_extreme(op)

    def grid(self, ctx: ChainContext) -> np.ndarray:
        op = np.clip(ctx.travel(ctx.op), 0.0, 100.0)
        lo = np.unique(np.percentile(op, PERCENTILES))
        hi = np.unique(np.percentile(op, [100.0 - p for p in PERCENTILES]))
        rows = [(v, 100.0) for v in lo if v > 0.0] + [(0.0, v) for v in hi if v < 100.0]
        return np.array(rows, dtype=float).reshape(-1, 2)

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        lo_stop, hi_stop = ctx.stops
        step = max(ctx.op_span * 100.0 / (hi_stop - lo_stop) / 20.0, 1e-3)
        offsets = step * np.linspace(-1.5, 1.5, 31)
        lo, hi = float(best[0]), float(best[1])
        if lo > 0.0:
            rows = [(np.clip(lo + d, 1e-6, hi - 1e-6), hi) for d in offsets]
        else:
            rows = [(lo, np.clip(hi + d, lo + 1e-6, 100.0 - 1e-6)) for d in offsets]
        return np.vstack([best[None, :], np.array(rows)])

    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        x2 = x[:, None] if x.ndim == 1 else x
        return np.clip(x2, params[:, 0][None, :], params[:, 1][None, :])

    def parameters(self, p: np.ndarray) -> dict:
        return {"lo": round(float(p[0]), 3) if p[0] > 0.0 else None,
                "hi": round(float(p[1]), 3) if p[1] < 100.0 else None}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        """``p`` in OP's units, NaN for the side without a limit (see ``explain.findings``)."""
        where = " travel" if units.strip() == "%" else ""
        if np.isfinite(p[0]):
            return f"saturation: no less flow below OP {p[0]:.4g}{units}{where}"
        return f"saturation: no more flow above OP {p[1]:.4g}{units}{where}"

    def identity(self) -> np.ndarray:
        return np.array([0.0, 100.0])


register(Saturation())
