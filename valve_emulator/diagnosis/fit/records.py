r"""The records the search passes around: a fitted model, a cost surface, an option of a round.

All are frozen; the fitting machines (:mod:`~valve_emulator.diagnosis.fit.scorer`,
:mod:`~valve_emulator.diagnosis.fit.fitter`, :mod:`~valve_emulator.diagnosis.explain.search`) create them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from valve_emulator.diagnosis.fit.chain import Active
from valve_emulator.diagnosis.fit.linear import LinearFit

__all__ = ["Model", "Surface", "Option"]


@dataclass(frozen=True, eq=False, kw_only=True)
class Model:
    """A complete model: active physics, the fitted linear part and its scores."""

    active: tuple[Active, ...]
    fit: LinearFit
    delay_free: bool
    k: int
    bic: float
    heldout: float
    y_hat: np.ndarray   # scaled PV prediction over the whole record
    flow: np.ndarray    # chain output (T,)
    target: np.ndarray | None = None  # what the linear part was fitted to, when an output candidate made it

    def by_slot(self) -> dict[str, Active]:
        return {a.slot: a for a in self.active}

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.active)


@dataclass(frozen=True, eq=False, kw_only=True)
class Surface:
    """Fit-part SSE over a candidate's parameter rows (minimised over the delays the option allowed).

    ``load_model``: the SSE was scored through the drifting-load noise model's prefilter (a late valve's second
    fit, :func:`~valve_emulator.diagnosis.explain.onset.late_options`), not in the search's own domain; its
    shape over the rows is comparable, its numbers are not the search's."""

    candidate: str
    params: np.ndarray
    sse: np.ndarray
    n: int
    load_model: bool = False


@dataclass(frozen=True, eq=False, kw_only=True)
class Option:
    """One way to extend the current model, fully fitted."""

    added: tuple[str, ...]
    model: Model
    coarse: Surface | None
    scan: Surface | None
    fine: Surface | None

    @property
    def label(self) -> str:
        return " + ".join(self.added)
