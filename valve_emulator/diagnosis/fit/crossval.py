r"""Two-fold blocked cross-validation of a fitted model: the held-out fit of searches without a nominal model.

Each fold of :func:`~valve_emulator.diagnosis.fit.data.folds` re-fits the model's linear part (poles, dead time,
taps, offsets; with an ``output`` candidate, the two together by backfitting) on the fold's fit block and
predicts its held-out block by free-run simulation from the recorded OP. The chain's own parameters (S and
J of a valve, a lag, a limit) are kept at their whole-record values: they are few, and re-searching their
grids per fold would double the cost; so this validates the *structure* and the linear part, and BIC on
the whole record (with the ΔBIC threshold) guards the valve parameters. The two held-out blocks are pooled:

.. math::  \mathrm{fit}_{cv} = 100\Big(1 - \sqrt{\textstyle\sum_{b}\sum_{k \in b}(y_k - \hat y^{(b)}_k)^2}
           \Big/ \sqrt{\textstyle\sum_{b}\sum_{k\in b}(y_k - \bar y_b)^2}\Big)

(:math:`\hat y^{(b)}` the prediction of the fold that held block b out, :math:`\bar y_b` the block's mean),
the same form as :func:`~valve_emulator.diagnosis.fit.data.fit_percent`, in percent.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from valve_emulator.diagnosis.fit.backfit import backfit
from valve_emulator.diagnosis.fit.data import folds
from valve_emulator.diagnosis.fit.linear import on_pv, polish
from valve_emulator.diagnosis.fit.records import Model
from valve_emulator.diagnosis.fit.scorer import Scorer

__all__ = ["cross_validated_fit", "with_cv"]


def _predict(scorer: Scorer, model: Model, window: tuple[int, int]) -> np.ndarray:
    """The model re-fitted on ``window`` and replayed over the whole record (scaled PV)."""
    p, st = scorer.p, model.fit.structure
    kw = scorer.polish_kw(model.delay_free)
    out = model.by_slot().get("output")
    if out is not None:
        ctx = replace(scorer.ctx(model), window=window)
        return backfit(model.flow, p.y, window, st, p.dt, out.candidate, out.params, ctx, prefilter=scorer.lam,
                       polish_kw=kw).y_hat
    fit = polish(model.flow, p.y, window, st, p.dt, **kw)
    level = fit if scorer.lam is None else on_pv(fit, model.flow, p.y, window, p.dt)
    return level.predict(model.flow, p.dt)


def cross_validated_fit(scorer: Scorer, model: Model, *, on_pv: bool = False) -> float:
    """Pooled two-fold held-out fit (%) of ``model`` (see the module docstring), in the problem's validation
    domain (:meth:`~valve_emulator.diagnosis.fit.data.Problem.validated`: what the search's rule compares), or
    ``on_pv`` on PV itself (what is reported)."""
    p = scorer.p
    domain = (lambda y: y) if on_pv else p.validated
    y = domain(p.y)
    err = dev = 0.0
    for fit_window, (a, b) in folds(p):
        if b - a < 2 or fit_window[1] - fit_window[0] < 2:
            continue
        y_hat = domain(_predict(scorer, model, fit_window))
        err += float(np.sum((y[a:b] - y_hat[a:b]) ** 2))
        dev += float(np.sum((y[a:b] - np.mean(y[a:b])) ** 2))
    return float("nan") if dev == 0.0 else 100.0 * (1.0 - np.sqrt(err / dev))


def with_cv(scorer: Scorer, model: Model) -> Model:
    """``model`` with its ``heldout`` filled in by :func:`cross_validated_fit` (itself if already there)."""
    if not np.isnan(model.heldout):
        return model
    return replace(model, heldout=cross_validated_fit(scorer, model))
