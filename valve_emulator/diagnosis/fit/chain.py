r"""The model's signal chain: OP → actuator → valve → characteristic → limit → flow, slot by slot.

A slot holds either an *active* candidate with fixed parameters, the nominal model's element (the
nominal valve's S and J, the nominal characteristic; no actuator dynamics), or — for the candidate under
search — a whole grid of parameter vectors, which turns the signal from one column into ``n``. Slots
before the gridded one are computed once and shared by every column.

The actuator and valve slots act on OP in the search's frame; the characteristic and limit slots on travel
(0–100 % between the travel stops, :meth:`~valve_emulator.diagnosis.candidates.base.ChainContext.travel`), and
the flow goes back to the search's frame after them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from valve_emulator.diagnosis.candidates.base import Candidate, ChainContext
from valve_emulator.diagnosis.candidates.valve_start import PRE_ROLL, valve_output
from valve_emulator.physics._arrays import kernel_array
from valve_emulator.physics.signal_chain import Characteristic

__all__ = ["Active", "CHAIN_SLOTS", "run_chain"]

#: Slots that transform the signal, in order (the dead time is part of the linear fit; ``output`` candidates
#: act after the plant, see :mod:`~valve_emulator.diagnosis.fit.backfit`). The nominal model has no limit.
CHAIN_SLOTS = ("actuator", "valve", "characteristic", "limit")
#: The first slot that acts on travel (it and the slots after it).
_FIRST_ON_TRAVEL = "characteristic"


@dataclass(frozen=True, eq=False)
class Active:
    """A candidate in the model with its parameter vector."""

    candidate: Candidate
    params: np.ndarray

    @property
    def name(self) -> str:
        return self.candidate.name

    @property
    def slot(self) -> str:
        return self.candidate.slot


def _nominal(slot: str, x: np.ndarray, ctx: ChainContext, S: float, J: float, in_range: bool = False) -> np.ndarray:
    if slot == "valve" and S > 0.0:
        n = 1 if x.ndim == 1 else x.shape[1]
        mv = valve_output(x, np.full(n, S), np.full(n, J), np.full(n, PRE_ROLL), ctx)
        return mv[:, 0] if x.ndim == 1 else mv
    if slot == "characteristic" and ctx.characteristic[0] != "linear":
        return Characteristic(*ctx.characteristic).flow(x)
    # in_range: x lies within 0–100 or is NaN (a valve's MV on the travel scale of OP), where the check below finds
    # nothing (a NaN makes min and max NaN, and neither comparison holds); at 10^5 samples its two passes over a chunk
    # of 64 flows were 1 of 16 CPU seconds
    if slot == "characteristic" and not in_range and (x.min() < 0.0 or x.max() > 100.0):
        return np.clip(x, 0.0, 100.0)  # the linear curve: travel stops at 0/100 (valve outputs never
    return x                           # leave them, so most calls skip the copy)


@numba.njit(cache=True, nogil=True)
def _travel_and_back(x, lo, to_travel, from_travel, out):  # pragma: no cover - compiled
    # ChainContext.travel, the linear characteristic's clip at the travel stops and ChainContext.from_travel, element
    # by element: the same operations on the same numbers. (The clip of a whole signal when any element is out of
    # range leaves the elements in range as they are, so it is a clip of each element.)
    T, n = x.shape
    for k in range(T):
        for j in range(n):
            v = (x[k, j] - lo) * to_travel
            if v < 0.0:
                v = 0.0
            elif v > 100.0:
                v = 100.0
            out[k, j] = lo + v * from_travel


def _plain_tail(active: dict[str, Active], grid_candidate: Candidate | None, ctx: ChainContext) -> bool:
    """Whether the slots on travel are the nominal linear characteristic and no limit, on a travel scale that
    differs from OP's: the tail of the chain is then a clip at the travel stops, which :func:`_travel_and_back`
    makes in one pass (numpy's took six passes over the signal and four arrays)."""
    on_travel = CHAIN_SLOTS[CHAIN_SLOTS.index(_FIRST_ON_TRAVEL):]
    return (ctx.stops != (0.0, 100.0) and ctx.characteristic[0] == "linear" and not any(s in active for s in on_travel)
            and (grid_candidate is None or grid_candidate.slot not in on_travel))


def _through_travel(x: np.ndarray, ctx: ChainContext) -> np.ndarray:
    """The chain's tail of :func:`_plain_tail` for ``x`` (T,) or (T, n): (T, n)."""
    lo, hi = ctx.stops
    x2 = kernel_array(x[:, None] if x.ndim == 1 else x)
    out = np.empty(x2.shape)
    _travel_and_back(x2, float(lo), 100.0 / (hi - lo), (hi - lo) / 100.0, out)
    return out


def run_chain(op: np.ndarray, active: dict[str, Active], ctx: ChainContext, *, nominal_valve=(0.0, 0.0),
              grid_candidate: Candidate | None = None, grid: np.ndarray | None = None) -> np.ndarray:
    """Flow (T, n) for ``n`` grid rows (n = 1 without a grid).

    Parameters
    ----------
    op : recorded OP (T,).
    active : active candidates by slot.
    ctx : chain context (dt, valve model, nominal characteristic ...).
    nominal_valve : ``(S, J)`` of the nominal valve, used when no valve candidate is active.
    grid_candidate, grid : the candidate under search and its parameter rows (n, p).
    """
    x = np.asarray(op, dtype=float)
    in_range = False   # x lies within 0–100 or is NaN (ChainCandidate.output_in_range)
    for slot in CHAIN_SLOTS:
        if slot == _FIRST_ON_TRAVEL:
            if _plain_tail(active, grid_candidate, ctx):
                return _through_travel(x, ctx)
            in_range = in_range and ctx.stops == (0.0, 100.0)   # ctx.travel leaves x as it is
            x = ctx.travel(x)
        if grid_candidate is not None and slot == grid_candidate.slot:
            x = grid_candidate.apply(x, grid, ctx)
            in_range = bool(getattr(grid_candidate, "output_in_range", False))
        elif slot in active:
            a = active[slot]
            n = 1 if x.ndim == 1 else x.shape[1]
            y = a.candidate.apply(x, np.repeat(a.params[None, :], n, axis=0), ctx)
            x = y[:, 0] if x.ndim == 1 else y
            in_range = bool(getattr(a.candidate, "output_in_range", False))
        else:
            x = _nominal(slot, x, ctx, *nominal_valve, in_range=in_range)
            if slot == "valve" and nominal_valve[0] > 0.0:
                in_range = True
            elif slot == "characteristic" and ctx.characteristic[0] != "linear":
                in_range = False
    x = ctx.from_travel(x)
    return x[:, None] if x.ndim == 1 else x
