r"""Candidate ``characteristic``: the valve's inherent flow characteristic differs from the nominal one.

Flow through the valve is ``f(MV)`` on the travel x ∈ [0, 1] (ISA-75.11; Choudhury et al. 2005): linear
``x``, equal percentage ``R^(x−1)`` with rangeability R, quick opening ``√x``
(:class:`~valve_emulator.physics.signal_chain.Characteristic`). Its signature is a process gain that
depends on the operating point: the residual of a linear-valve model correlates with the OP *level*.

Parameters: ``kind`` (index into ``CHARACTERISTICS``; a label) and ``R``; one parameter for BIC. The grid
holds every kind except the nominal one, and equal percentage at R ∈ {3 … 400} (log-spaced) unless the
nominal is that very curve; :meth:`refine` searches R on a finer log grid, never beyond the grid's ends. The
top, :data:`R_MAX`, is steeper than any valve's inherent curve (catalogues give 20–100); an estimate there
says only "at least that steep", so it is declared a search edge (:meth:`bounds`) and reported as a bound.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainCandidate, ChainContext, TwinRole, register, said
from valve_emulator.physics.signal_chain import CHARACTERISTICS, DEFAULT_RANGEABILITY, Characteristic

__all__ = ["FlowCharacteristic", "R_GRID", "R_MAX", "R_MIN"]

#: Rangeabilities tried by the coarse grid.
R_GRID = (3.0, 5.0, 8.0, 12.0, 20.0, 30.0, 50.0, 80.0, 150.0, 250.0, 400.0)
#: The steepest equal-percentage curve searched (the top of the grid).
R_MAX = R_GRID[-1]
#: The flattest one: R → 1 is the linear curve, itself a candidate, so this end is a limit of the physics.
R_MIN = 1.05
_EQP = CHARACTERISTICS.index("equal_percentage")


def _curve(p: np.ndarray) -> Characteristic:
    return Characteristic(CHARACTERISTICS[int(p[0])], p[1] if p[1] > 1 else DEFAULT_RANGEABILITY)


class FlowCharacteristic(ChainCandidate):
    name: ClassVar[str] = "characteristic"
    slot: ClassVar[str] = "characteristic"
    param_names: ClassVar[tuple[str, ...]] = ("kind", "R")
    n_params: ClassVar[int] = 1
    cause_rank: ClassVar[int | None] = 40
    needs_span: ClassVar[bool] = True   # a curve over travel: where 0 and 100 % lie must be known
    twin_role: ClassVar[TwinRole | None] = TwinRole.CHARACTERISTIC

    def grid(self, ctx: ChainContext) -> np.ndarray:
        nominal_kind, nominal_r = ctx.characteristic
        rows = []
        for i, kind in enumerate(CHARACTERISTICS):
            if kind == "equal_percentage":
                rows += [(i, r) for r in R_GRID if not (nominal_kind == kind and np.isclose(r, nominal_r))]
            elif kind != nominal_kind:
                rows.append((i, 0.0))
        return np.array(rows, dtype=float)

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        if int(best[0]) != _EQP:
            return best[None, :]
        R = np.unique(np.clip(best[1] * np.exp(np.linspace(-0.45, 0.45, 19)), R_MIN, R_MAX))
        return np.vstack([best[None, :], np.column_stack([np.full(R.size, _EQP), R])])

    def bounds(self, ctx: ChainContext) -> dict[str, tuple[float | None, float | None]]:
        return {"R": (None, R_MAX)}

    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        n = params.shape[0]
        if x.ndim == 2 and np.all(params == params[0]):  # one curve for many columns: one array call
            return _curve(params[0]).flow(x)
        out = np.empty((x.shape[0], n))
        for c in range(n):  # a grid of a dozen curves over one signal
            out[:, c] = _curve(params[c]).flow(x if x.ndim == 1 else x[:, c])
        return out

    def parameters(self, p: np.ndarray) -> dict:
        kind = CHARACTERISTICS[int(p[0])]
        return {"type": kind, "R": round(float(p[1]), 3) if kind == "equal_percentage" else None}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        kind = CHARACTERISTICS[int(p[0])]
        if kind == "equal_percentage":
            curve = f"an equal-percentage flow characteristic: {said('R', 'R', p[1], '.0f', edges)}"
            if edges and "R" in edges:   # the top: steeper than any valve's own curve
                curve += (", steeper than any valve's inherent curve (catalogues give 20–100): a gain that rises "
                          "with OP more than a valve explains, as likely the process's or the load's as the valve's")
            return curve
        return f"a {kind.replace('_', '-')} flow characteristic"


register(FlowCharacteristic())
