r"""Does the valve's evidence survive a drifting load? A second look at a valve finding, under another noise model.

The search scores models by their free-run (output-error) fit, with an AR(1) error model for BIC
(:mod:`~valve_emulator.diagnosis.fit.scorer`). That error model is stationary: it expects PV to come back to
what OP explains. A slow, wandering load that the controller compensates breaks the assumption in a way
that imitates a stuck valve: OP drifts to cancel the load while PV holds its set point, so a linear valve
replays OP into PV swings that never happened, and a valve that does not move (a band S) replays them
away. Simulated linear loops under a random-walk load are called stiction that way, with ΔBIC in the
hundreds; on plant data a non-sticky flow loop whose OP wanders while PV sits on its set point is too.

This module re-scores a valve finding by the prediction-error method with the noise model of a random-walk
load plus white measurement noise — the local-level model, whose innovation form is ARIMA(0,1,1)
(Harvey, *Forecasting, structural time series models and the Kalman filter*, 1989, §4.1):

.. math::  \mathrm{pv}_k = G(q)\,\mathrm{flow}_k + \frac{1 - \lambda q^{-1}}{1 - q^{-1}}\, e_k ,
           \qquad e_k \text{ white},

so the one-step prediction errors are :math:`e = L(q)(\mathrm{pv} - G\,\mathrm{flow})` with
:math:`L(q) = (1 - q^{-1})/(1 - \lambda q^{-1})`, the package's high-pass prefilter
(:func:`~valve_emulator.diagnosis.fit.linear.highpass`; Ljung, *System Identification*, 2nd ed., §7.2 and §14.4:
a fixed noise model is a prefilter). λ, the noise model's one parameter (λ = 0: the load is a pure random
walk; λ → 1: no load), is chosen per model from :data:`LAMBDAS` by BIC; the linear part (poles, dead time,
taps) is re-fitted at every λ (:func:`~valve_emulator.diagnosis.fit.linear.polish`); the valve keeps the
parameters the search found. Both models — with and without the valve finding — are scored the same way,
and :func:`load_delta_bic` returns BIC without minus BIC with (k + 1 parameters, λ counted).

What it is used for: the answer of :func:`~valve_emulator.diagnosis.assess.decision.assess` says whether a
stiction call *survives a drifting load* (ΔBIC ≥ :data:`~valve_emulator.diagnosis.explain.search.DELTA_BIC` here
too) — strong evidence — or not: a linear valve with a compensated drifting load explains the record about
as well. It qualifies the answer and does not change it: on the labelled plant data of ``docs/real-data.md``
requiring it would remove the one false stiction call and five true ones (one valve each way), which is
reported there as a sensitivity study. On simulated loops it separates cleanly: linear loops under a
random-walk load give ΔBIC ≤ 3, sticky ones (with or without such a load) several hundred.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from valve_emulator.diagnosis.fit.cost import bic
from valve_emulator.diagnosis.fit.linear import LinearStructure, delayed_regressors, filter_inputs, highpass, polish
from valve_emulator.diagnosis.fit.records import Model
from valve_emulator.diagnosis.fit.scorer import Scorer

__all__ = ["LAMBDAS", "STATIC_PIECES", "Memory", "Swallowed", "family_delta_bic", "input_delta_bic", "load_bic",
           "load_bic_of", "load_bic_on", "load_delta_bic", "noise_only_bic", "remembered", "swallowed"]

#: The noise model's λ searched (0: a pure random-walk load; 0.98: a load that wanders over ~50 samples).
LAMBDAS = (0.0, 0.3, 0.5, 0.7, 0.8, 0.9, 0.95, 0.98)
#: Pieces of the single-valued map of OP that :func:`remembered` fits in place of any flow characteristic: straight
#: between knots at OP's quantiles 1/6 … 5/6 (six pieces, seven coefficients with the level): a smooth monotone
#: curve over the span OP visits, as a valve's inherent characteristic is (equal percentage, quick opening), is
#: followed piece by piece wherever OP spends its time.
STATIC_PIECES = 6
#: Nelder–Mead evaluations per re-fit of the linear part (it starts from the search's solution).
_EVALS = 80


def load_bic_of(flow: np.ndarray, y: np.ndarray, window: tuple[int, int], structure: LinearStructure, dt: float,
                *, k: int, free_delay: bool, max_delay: float, extra: np.ndarray | None = None
                ) -> tuple[float, float]:
    """BIC of the linear part ``structure`` driven by ``flow`` (T,) for ``y`` (T,) on ``window`` under the
    drifting-load noise model, with ``k`` parameters besides λ, and the λ of :data:`LAMBDAS` that gives it.

    The poles (and the dead time, within [0, ``max_delay``] s, when ``free_delay``) start from ``structure``
    and are re-fitted at every λ; ``extra`` (T, m) regressors are fitted jointly.
    """
    best = (float("inf"), float("nan"))
    for lam in LAMBDAS:
        fit = polish(flow, y, window, structure, dt, free_delay=free_delay, delay_bounds=(0.0, max_delay),
                     prefilter=lam, max_evals=_EVALS, extra=extra)
        best = min(best, (bic(fit.sse, fit.n, k + 1), lam))
    return best


def load_bic(scorer: Scorer, model: Model) -> tuple[float, float]:
    """:func:`load_bic_of` for a model of the search (its chain output, linear structure and parameters).

    Remembered per model on the scorer: the strength of a valve finding and :func:`input_delta_bic` often ask
    for the same final model.
    """
    hit = scorer.memo.get(id(model))
    if hit is not None and hit[0] is model:
        return hit[1]
    result = load_bic_on(scorer, model, scorer.p.train)
    scorer.memo[id(model)] = (model, result)
    return result


def load_bic_on(scorer: Scorer, model: Model, window: tuple[int, int]) -> tuple[float, float]:
    """:func:`load_bic_of` for a model of the search on ``window`` (samples; its linear part re-fitted there at
    every λ)."""
    p = scorer.p
    out = model.by_slot().get("output")
    extra = None if out is None else out.candidate.regressors(out.params, scorer.ctx(model))
    return load_bic_of(model.flow, p.y, window, model.fit.structure, p.dt, k=model.k,
                       free_delay=model.delay_free, max_delay=scorer.dmax, extra=extra)


def family_delta_bic(first: tuple[Scorer, Model], second: tuple[Scorer, Model]) -> float:
    """BIC of the first search's model minus that of the second's, both under the drifting-load noise model on
    the samples both fitted (the later start of their fit parts): how much better the second explains PV once a
    drifting load is allowed for. The two may come from searches in different cost domains (PV, prefiltered
    PV) and plant families; this scores both on PV itself with one noise model.

    Why not the free-run fit of PV: an integrating plant turns a wandering load into a ramp that a free run
    never catches up with, so a level loop's right model can predict held-out PV far worse than a slow
    first-order one (fits of −300 % against −1 %); the prediction-error view with a random-walk load is the
    comparison that treats both families alike.
    """
    (s1, m1), (s2, m2) = first, second
    window = (max(s1.p.train[0], s2.p.train[0]), min(s1.p.train[1], s2.p.train[1]))
    return load_bic_on(s1, m1, window)[0] - load_bic_on(s2, m2, window)[0]


def load_delta_bic(scorer: Scorer, without: Model, with_: Model) -> float:
    """BIC of ``without`` minus that of ``with_``, both under the drifting-load noise model (see above)."""
    return load_bic(scorer, without)[0] - load_bic(scorer, with_)[0]


def noise_only_bic(y: np.ndarray, window: tuple[int, int]) -> float:
    """BIC of ``y`` on ``window`` as the drifting-load noise model alone — a level and the load, no input — at
    the λ of :data:`LAMBDAS` that fits best (2 parameters: the level and λ)."""
    w0, w1 = window
    best = float("inf")
    for lam in LAMBDAS:
        e = highpass(y, lam)[w0:w1]
        e = e - e.mean()
        best = min(best, bic(float(e @ e), e.size, 2))
    return best


def input_delta_bic(scorer: Scorer, model: Model) -> float:
    """How much OP explains PV once a drifting load is allowed for: BIC of PV as load noise alone
    (:func:`noise_only_bic`) minus BIC of ``model`` (:func:`load_bic`), both under the drifting-load noise model.

    The free-run fit of a model on plant data can be below zero although the model captures what OP does to PV:
    the load wanders, and a free-run replay never catches up with it. This figure asks the question the
    free-run fit cannot answer there — does the model explain PV's response to OP — with the same noise model
    and the same ΔBIC rule as the strength of a stiction call.
    """
    return noise_only_bic(scorer.p.y, scorer.p.train) - load_bic(scorer, model)[0]


@dataclass(frozen=True)
class Swallowed:
    """Whether the moves of OP that a valve band swallows reach PV (:func:`swallowed`).

    Attributes
    ----------
    bic_valve : BIC of PV from the valve's output alone, through the plant, under the drifting-load noise model.
    bic_leaking : the same with OP's swallowed moves let through the same plant too, with a coefficient of their
        own.
    share : how much of the swallowed moves reach PV, relative to the valve's own moves (the ratio of their
        fitted coefficients: 1 for a valve that passes every move, 0 for one that is stuck while OP moves
        inside its band).
    gain : the valve's own coefficient in that regression (PV per unit of OP through the plant's unit-gain
        response; for an integrator, PV's rate per unit of OP per second), at the λ that gives ``bic_leaking``.
    """

    bic_valve: float
    bic_leaking: float
    share: float
    gain: float = float("nan")

    @property
    def delta_bic(self) -> float:
        """How much better the swallowed moves explain PV (positive: they do)."""
        return self.bic_valve - self.bic_leaking


def _through(u: np.ndarray, structure: LinearStructure, dt: float) -> np.ndarray:
    """``u`` through the plant's poles and dead time (the first tap of the search's regressors, unit gain)."""
    return delayed_regressors(filter_inputs(u, structure, dt), structure.delay / dt, 1)[:, 0]


def swallowed(pv: np.ndarray, op: np.ndarray, valve: np.ndarray, structure: LinearStructure, dt: float,
              start: int) -> Swallowed:
    """Do the moves of OP that a valve band swallows reach PV? PV from ``start`` on, under the drifting-load
    noise model (λ of :data:`LAMBDAS` chosen by BIC for each), regressed on the valve's output ``valve`` through
    the identified plant ``structure``, then on that and on what the valve swallows (``op − valve``) through the
    same plant, each with its own coefficient.

    Why: a band S fitted to a loop says the valve holds while OP moves inside it. Where the valve really is
    stuck, those moves leave PV alone (a coefficient near 0); where it is healthy and the band stands in for
    something else (the controller's small answers to a wandering load, on a level loop), they move PV as the
    valve's own moves do. The test asks the band's claim directly, in the one-step view that a wandering load
    does not fool (the noise model of :func:`load_delta_bic`)."""
    through_valve, through_rest = _through(valve, structure, dt), _through(op - valve, structure, dt)
    best_without = best_with = float("inf")
    share = gain = float("nan")
    for lam in LAMBDAS:
        y = highpass(pv, lam)[start:]
        a, b = highpass(through_valve, lam)[start:], highpass(through_rest, lam)[start:]
        one = np.ones_like(y)
        without, sse0 = _least_squares(np.column_stack([a, one]), y)
        with_, sse1 = _least_squares(np.column_stack([a, b, one]), y)
        best_without = min(best_without, bic(sse0, y.size, 3))
        fit = bic(sse1, y.size, 4)
        if fit < best_with:
            best_with = fit
            gain = float(with_[0])
            share = float(with_[1] / with_[0]) if with_[0] != 0.0 else float("nan")
    return Swallowed(bic_valve=best_without, bic_leaking=best_with, share=share, gain=gain)


def _least_squares(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """Coefficients and residual sum of squares of ``y`` on the columns of ``x``."""
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
    r = y - x @ beta
    return beta, float(r @ r)


@dataclass(frozen=True)
class Memory:
    """Whether PV shows the memory of a valve band beyond any single-valued map of OP (:func:`remembered`).

    Attributes
    ----------
    delta_bic : BIC of PV from a single-valued map of OP through the plant minus BIC with the band's memory added
        (the valve's output minus OP, through the same plant), under the drifting-load noise model: positive
        when the memory explains PV better.
    share : the memory's coefficient relative to the valve's own (1 for PV that follows a valve stuck in its band,
        0 for PV that follows OP through a curve), with the valve's sign.
    """

    delta_bic: float
    share: float


def _static_columns(op: np.ndarray, start: int) -> np.ndarray:
    """OP and its hinges at the knots of :data:`STATIC_PIECES` (OP's quantiles from ``start`` on): a continuous map
    of OP, straight between the knots. Their span is the same for any affine map of OP, reversed or not."""
    knots = np.quantile(op[start:], np.arange(1, STATIC_PIECES) / STATIC_PIECES)
    return np.column_stack([op] + [np.maximum(op - k, 0.0) for k in knots])


def remembered(pv: np.ndarray, op: np.ndarray, valve: np.ndarray, structure: LinearStructure, dt: float,
               start: int) -> Memory:
    """Does PV remember where a valve band left the valve, beyond what any flow characteristic could make of OP?
    PV from ``start`` on, under the drifting-load noise model (λ of :data:`LAMBDAS` chosen by BIC for each),
    regressed on a single-valued map of OP (:func:`_static_columns`) through the plant ``structure``, then on that
    and on the band's memory, the valve's output ``valve`` minus OP, through the same plant.

    Why: a flow characteristic, whatever its kind, is a static map: at one OP it gives one flow. Friction is
    hysteresis: at one OP the valve sits where it last stuck, higher after a fall of OP than after a rise. A model
    with a characteristic and none with friction explains a sticky loop through the map's slopes; whether the
    record holds what no map can make is asked here, with the map made as free as a smooth curve over OP's span
    needs (so a characteristic at the edge of the range searched, a bound, does not stand in for it)."""
    static = [_through(c, structure, dt) for c in _static_columns(op, start).T]
    memory, own = _through(valve - op, structure, dt), _through(valve, structure, dt)
    best_map = best_with = float("inf")
    share = float("nan")
    for lam in LAMBDAS:
        y = highpass(pv, lam)[start:]
        one = np.ones_like(y)
        cols = np.column_stack([highpass(c, lam)[start:] for c in static] + [one])
        m = highpass(memory, lam)[start:]
        _, sse0 = _least_squares(cols, y)
        beta, sse1 = _least_squares(np.column_stack([cols, m]), y)
        best_map = min(best_map, bic(sse0, y.size, cols.shape[1] + 1))
        fit = bic(sse1, y.size, cols.shape[1] + 2)
        if fit < best_with:
            best_with = fit
            gain, _ = _least_squares(np.column_stack([highpass(own, lam)[start:], one]), y)
            share = float(beta[-1] / gain[0]) if gain[0] != 0.0 else float("nan")
    return Memory(delta_bic=best_map - best_with, share=share)
