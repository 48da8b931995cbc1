r"""Fitting the linear part together with an ``output`` candidate (a quantiser, an external disturbance).

Such a candidate acts after the plant, so the model is

.. math::  \hat{\mathrm{pv}} = \mathcal{O}_\eta\big(G(q)\,u\big),

with ``u`` the chain's flow, G the linear part of :mod:`~valve_emulator.diagnosis.fit.linear` and
:math:`\mathcal O_\eta` the candidate (parameters η). It is fitted by *backfitting* (Hastie & Tibshirani,
*Generalized Additive Models*, 1990, ch. 4): alternately (a) the candidate turns the measured PV into the
target the linear part should match, given the linear part's current prediction (:meth:`Candidate.adjust`:
PV minus the fitted sinusoid; the point of each reading's quantisation interval nearest to the
prediction), and (b) the linear part is re-fitted to that target by least squares. For an additive
disturbance both steps are projections and the iteration converges to the joint least-squares fit; for the
quantiser it is the alternating minimisation of the dead-zone loss. An *additive* term linear in its
coefficients (a sinusoid of given period, :meth:`Candidate.regressors`) is instead fitted jointly with the
linear part in one least-squares problem: backfitting converges slowly when the term and the replayed OP
are correlated, as they are in closed loop (OP answers the disturbance). :data:`ITERATIONS` rounds with the
poles held (the dead time, when a grid of them is given, re-chosen at every round as the best whole number
of samples), then one polish of the poles and dead time (variable projection, as every other fit) and a
final round. The coarse stage of a search runs the quick form (no polish) from every pole hypothesis, as
chain candidates' coarse stages do, so an output candidate is not stuck with a linear part that was fitted
without it (and so biased by it).

While a model with an output candidate is extended further, the candidate's target is held fixed and the
next candidate is fitted to it (:meth:`~valve_emulator.diagnosis.fit.scorer.Scorer.aim`); the refinement that
follows each acceptance re-fits the earlier pieces with the new one in place.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from valve_emulator.diagnosis.candidates.base import Candidate, ChainContext
from valve_emulator.diagnosis.fit.linear import (
    LinearFit,
    LinearStructure,
    delay_grid_sse,
    filter_inputs,
    fit_filtered,
    fit_one,
    highpass,
    input_grid_sse,
    polish,
)

__all__ = ["ITERATIONS", "Backfit", "Filtered", "backfit", "backfit_sse"]

#: Backfitting rounds with the linear structure held (then one polish and a final round).
ITERATIONS = 4


@dataclass(frozen=True, eq=False)
class Backfit:
    """Result of :func:`backfit`.

    Attributes
    ----------
    fit : the linear part in the search's cost domain (prefiltered for an integrating plant); its ``sse``
        on the final target is what BIC sees.
    level : the linear part fitted to the final target in the PV domain (its prediction is the model's
        before the candidate).
    target : the final target (scaled PV units).
    params : the candidate's row with its internally fitted entries.
    y_hat : the whole model's prediction of the recorded (scaled) PV.
    """

    fit: LinearFit
    level: LinearFit
    target: np.ndarray
    params: np.ndarray
    y_hat: np.ndarray


class Filtered:
    """The flow a backfit drives the linear part with, filtered by the structure's poles (:func:`~valve_emulator.
    diagnosis.fit.linear.filter_inputs`), and its target, both in the cost domain (``prefilter``): what
    :func:`~valve_emulator.diagnosis.fit.linear.fit_one` makes of them at every call. Neither depends on the dead
    time nor on an output candidate's row, so the rows of one grid (:meth:`~valve_emulator.diagnosis.fit.fitter.
    Fitter.output_sse`) share one, each made once, when first asked for."""

    def __init__(self, flow: np.ndarray, y: np.ndarray, structure: LinearStructure, dt: float,
                 prefilter: float | None) -> None:
        self.flow, self.y, self.structure, self.dt, self.prefilter = flow, y, structure, dt, prefilter

    @cached_property
    def z(self) -> np.ndarray:
        """(T,) the filtered flow."""
        z = filter_inputs(self.flow, self.structure, self.dt)
        return z if self.prefilter is None else highpass(z, self.prefilter)

    @cached_property
    def target(self) -> np.ndarray:
        """(T,) the target."""
        return self.y if self.prefilter is None else highpass(self.y, self.prefilter)

    def matches(self, flow: np.ndarray, y: np.ndarray, structure: LinearStructure, dt: float,
                prefilter: float | None) -> bool:
        """Whether these are the arrays and the poles it was made for."""
        st, mine = structure, self.structure
        return (flow is self.flow and y is self.y and dt == self.dt and prefilter == self.prefilter
                and (st.taus, st.integrating, st.fixed_poles) == (mine.taus, mine.integrating, mine.fixed_poles))


def _project_out(x: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """``x`` (T,) or (T, n) minus its least-squares projection on the columns of ``basis`` (T, m)."""
    coef, *_ = np.linalg.lstsq(basis, x, rcond=None)
    return x - basis @ coef


def _best_delay(flow: np.ndarray, target: np.ndarray, window: tuple[int, int], st: LinearStructure, dt: float,
                delays: np.ndarray, prefilter: float | None, extra: np.ndarray | None = None) -> LinearStructure:
    """``st`` with the whole-sample dead time of ``delays`` that fits ``target`` best.

    With ``extra`` regressors the filtered input and the target are first cleared of them over the record
    (Frisch–Waugh–Lovell; exact for the target, approximate for delayed inputs — enough to rank dead times).
    """
    if extra is None:
        y = target if prefilter is None else highpass(target, prefilter)
        sse = input_grid_sse(flow, y, window, delays, st, dt, prefilter=prefilter)[0]
        return replace(st, delay=float(delays[int(np.argmin(sse))]) * dt)
    filtered = Filtered(flow, target, st, dt, prefilter)
    return _best_delay_joint(filtered, window, st, delays,
                             extra if prefilter is None else highpass(extra, prefilter))


def _best_delay_joint(filtered: Filtered, window: tuple[int, int], st: LinearStructure, delays: np.ndarray,
                      extra: np.ndarray) -> LinearStructure:
    """:func:`_best_delay` with ``extra`` regressors (in the cost domain), from the filtered flow and target."""
    z, y = _project_out(filtered.z[:, None], extra), _project_out(filtered.target, extra)
    sse = delay_grid_sse(z, y, window, delays, st, prefiltered=filtered.prefilter is not None)[0]
    return replace(st, delay=float(delays[int(np.argmin(sse))]) * filtered.dt)


def backfit(flow: np.ndarray, y: np.ndarray, window: tuple[int, int], structure: LinearStructure, dt: float,
            cand: Candidate, params: np.ndarray, ctx: ChainContext, *, prefilter: float | None = None,
            polish_kw: dict | None = None, iterations: int = ITERATIONS,
            delays: np.ndarray | None = None) -> Backfit:
    """Linear part + output candidate fitted on ``window`` (see the module docstring).

    ``polish_kw`` (keyword arguments of :func:`~valve_emulator.diagnosis.fit.linear.polish`; its ``prefilter``,
    if any, must be ``prefilter``) enables the polish of the poles and dead time; ``None`` keeps
    ``structure`` (the quick version the grids use). ``delays`` (whole samples) re-chooses the dead time at
    every round.
    """
    ctx = replace(ctx, window=tuple(window))
    extra = cand.regressors(params, ctx)
    if extra is not None:
        return _joint(flow, y, window, structure, dt, cand, params, ctx, extra, prefilter, polish_kw, delays)
    if delays is not None:
        structure = _best_delay(flow, y, window, structure, dt, delays, prefilter)
    level, target, params, structure = _rounds(flow, y, window, structure, dt, cand, params, ctx, iterations,
                                               delays, prefilter)
    if polish_kw is not None:
        structure = polish(flow, target, window, structure, dt, **{"prefilter": prefilter, **polish_kw}).structure
        level = fit_one(flow, target, window, structure, dt)
        target, params = cand.adjust(y, level.predict(flow, dt), params, ctx)
    fit = fit_one(flow, target, window, structure, dt, prefilter=prefilter)
    level = fit if prefilter is None else fit_one(flow, target, window, structure, dt)
    return Backfit(fit, level, target, params, cand.predict(level.predict(flow, dt), params, ctx))


def backfit_sse(flow: np.ndarray, y: np.ndarray, window: tuple[int, int], structure: LinearStructure, dt: float,
                cand: Candidate, params: np.ndarray, ctx: ChainContext, *, prefilter: float | None = None,
                iterations: int = ITERATIONS, delays: np.ndarray | None = None,
                filtered: Filtered | None = None) -> float:
    """``backfit(...).fit.sse`` of the quick form (no polish): what a grid row of an output candidate scores.

    The same steps up to that fit, without those only a model needs (the fit in the PV domain, the predictions,
    the candidate's final adjustment): a search scores dozens of rows and keeps one. ``filtered``: the flow and
    ``y`` filtered for ``structure`` (:class:`Filtered`), shared by the rows of a grid.
    """
    ctx = replace(ctx, window=tuple(window))
    extra = cand.regressors(params, ctx)
    if extra is not None:
        # Additive regressors: one least-squares problem, the flow and y filtered once for both fits.
        if filtered is None or not filtered.matches(flow, y, structure, dt, prefilter):
            filtered = Filtered(flow, y, structure, dt, prefilter)
        extra = extra if prefilter is None else highpass(extra, prefilter)
        if delays is not None:
            structure = _best_delay_joint(filtered, window, structure, delays, extra)
        return fit_filtered(filtered.z, filtered.target, window, structure, dt, prefiltered=prefilter is not None,
                            extra=extra).sse
    if delays is not None:
        structure = _best_delay(flow, y, window, structure, dt, delays, prefilter)
    level, target, params, structure = _rounds(flow, y, window, structure, dt, cand, params, ctx, iterations,
                                               delays, prefilter)
    return fit_one(flow, target, window, structure, dt, prefilter=prefilter).sse


def _rounds(flow, y, window, structure, dt, cand, params, ctx, iterations, delays, prefilter):
    """The backfit's alternation for a candidate without regressors of its own: the linear part fitted to the
    target, the candidate adjusted to the linear part's prediction, ``iterations`` times (the dead time re-chosen
    each round when ``delays`` is given). Returns ``(level, target, params, structure)``."""
    level = fit_one(flow, y, window, structure, dt)
    target = y
    for _ in range(iterations):
        target, params = cand.adjust(y, level.predict(flow, dt), params, ctx)
        if delays is not None:
            structure = _best_delay(flow, target, window, structure, dt, delays, prefilter)
        level = fit_one(flow, target, window, structure, dt)
    return level, target, params, structure


def _joint(flow, y, window, structure, dt, cand, params, ctx, extra, prefilter, polish_kw, delays) -> Backfit:
    """:func:`backfit` for an additive term: one least-squares problem, the term's regressors appended."""
    if delays is not None:
        structure = _best_delay(flow, y, window, structure, dt, delays, prefilter, extra)
    if polish_kw is not None:
        structure = polish(flow, y, window, structure, dt, extra=extra,
                           **{"prefilter": prefilter, **polish_kw}).structure
    fit = fit_one(flow, y, window, structure, dt, prefilter=prefilter, extra=extra)
    level = fit if prefilter is None else fit_one(flow, y, window, structure, dt, extra=extra)
    y_lin = level.predict(flow, dt)
    target, params = cand.adjust(y, y_lin, params, ctx)  # the term's coefficients given the joint linear part
    return Backfit(fit, level, target, params, cand.predict(y_lin, params, ctx))
