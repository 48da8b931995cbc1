r"""The nominal model is a prior: its linear part moves only when the data demand it.

Two lags in series are the same transfer function in either order, so closed-loop data cannot tell an
actuator lag the model leaves out from the plant's own time constant; only what the user believes about the
plant can. The search therefore fits every model by maximum a posteriori (MAP): each time constant τ_i of the
nominal plant has a log-normal prior, ln τ_i ~ N(ln τ_i,nom, σ²), σ = ln 1.25
(:data:`~valve_emulator.diagnosis.fit.linear.PRIOR_WIDTH`: the nominal plant trusted to within about 25 %),
and the cost minimised is −2 log posterior up to a constant,

.. math::  J(\vartheta) = N \ln \mathrm{SSE}(\vartheta) + \sum_i \big((\ln\tau_i - \ln\tau_{i,\mathrm{nom}})
           /\sigma\big)^2 ,

which is what every polish and every comparison of starts minimises
(:meth:`~valve_emulator.diagnosis.fit.scorer.Scorer.prior_penalty`). The steady-state gain gets the same
prior, ``((ln K − ln K_nom)/σ)²``; it is not in the search's cost because the data fix the gain far more
tightly than σ (its MAP and least-squares estimates agree to within their standard error), but it is in the
decision below.

When the search is done, :func:`settle` asks, group by group, whether the final model's linear part may stay
at the nominal values: the same model with the time constants held at the nominal ones (the parameters of a
candidate that trades off against them, the actuator lag, refined again around them; held parameters are not
counted by BIC) against the model with them
moved, by the penalised BIC

.. math::  \mathrm{BIC}_\mathrm{held} = N \ln(\mathrm{SSE}_\mathrm{held}/N) + (k - n_\tau) \ln N, \qquad
           \mathrm{BIC}_\mathrm{moved} = N \ln(\mathrm{SSE}/N) + k \ln N + \sum_i ((\ln\tau_i -
           \ln\tau_{i,\mathrm{nom}})/\sigma)^2 .

The group moves when the move passes the test every finding must pass
(:func:`~valve_emulator.diagnosis.explain.search.significant`):
:math:`\mathrm{BIC}_\mathrm{held} - \mathrm{BIC}_\mathrm{moved}` is at least
:data:`~valve_emulator.diagnosis.explain.search.DELTA_BIC` (10) *and* the held-out fit rises by at least
:data:`~valve_emulator.diagnosis.explain.search.DELTA_FIT` (0.5 points); otherwise the held model is the
answer. BIC alone is not enough: on a record the search's model does not match exactly, a plant time
constant halved can lower the BIC by tens for a held-out fit that does not move (97.64 → 97.66 %), and a
nominal value the user trusts is not given up for that. Then the same for the gain (one parameter), on the
model the first decision kept. Where holding the gain raises the penalised BIC by :data:`DELTA_BIC` or more (the
move could count), every finding of the chain is first refined again around the nominal gain (kept where that
lowers the BIC): the findings were fitted around the gain the search left, and the model that holds the gain must
be judged, and reported, with the findings that suit it — a valve's band and slip jump set the size of PV's
cycles through the gain (on the independent ``late_onset`` loops with their nominal model, draw 6 of the onset
property: the gain moved ×1.16 for exactly the 0.5 points, and J was 1.12 % for 1.89–1.97; refined around the
nominal gain, the move no longer lowers BIC by 10, and J is 1.69 %). Where holding it costs less, the move cannot
count whatever the refinement gives (it only lowers the held model's BIC), and the findings already fit the
nominal gain to within the threshold: they are not refined (refined everywhere, the proof cases' loop at 10,000
samples of ``bench/bench_diagnose.py``, whose gain holds at −8.7, took 1.13 times the CPU). The refinement's grids are
scored at the held gain (:func:`~valve_emulator.diagnosis.fit.linear.input_grid_sse`; they had fitted it
freely and chosen the band that suits the moved gain), and a finding that starts late is also searched afresh
there (:func:`~valve_emulator.diagnosis.explain.onset.late_afresh`). Where a finding starts late the gain moves
only where it also lowers the BIC under the drifting-load noise model by :data:`DELTA_BIC` — the rule every
option meets against a late lead: a gain shrunk to replay less of a wandering load before the onset is what the
free run asks for (the independent ``late_onset`` draw 10 with its model: the gain moved ×0.43 for a ΔBIC of
446, 18 *higher* under that noise model, and the band was S 2.39 % for 4.33; held, 4.03 %). Each test becomes a
:class:`~valve_emulator.diagnosis.explain.result.LinearMove`: from what, to what, the penalised ΔBIC and the
held-out fit each way. A dead time the search freed (the ``dead_time`` finding) is reported the same way from
its finding.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from valve_emulator.diagnosis.explain.onset import late_afresh, late_start
from valve_emulator.diagnosis.explain.result import Finding, LinearMove
from valve_emulator.diagnosis.explain.search import DELTA_BIC, DELTA_FIT, Search
from valve_emulator.diagnosis.fit.linear import PRIOR_WIDTH, fit_one
from valve_emulator.diagnosis.fit.records import Model

__all__ = ["settle", "dead_time_move", "nominal_gain"]


def nominal_gain(num, den) -> float:
    """Steady-state gain of ``num/den`` (an integrator's s drops out: gain per second)."""
    den = np.trim_zeros(np.asarray(den, dtype=float), "b")
    return float(num[-1] / den[-1])


def _decide(search: Search, moved: Model, held: Model, penalty: float, *, under_load: bool = False
            ) -> tuple[Model, float]:
    """The model kept and the penalised ΔBIC (held minus moved) of the move: it moves only when the penalised
    BIC falls by :data:`DELTA_BIC` and the held-out fit rises by :data:`DELTA_FIT` points — and, ``under_load``,
    when its BIC under the drifting-load noise model falls by :data:`DELTA_BIC` too."""
    delta = held.bic - (moved.bic + penalty)
    buys_fit = moved.heldout - held.heldout >= DELTA_FIT
    counts = delta >= DELTA_BIC and buys_fit and (not under_load or search.lower_under_load(moved, held))
    return (moved if counts else held), float(delta)


def _settle_poles(search: Search, model: Model) -> tuple[Model, list[LinearMove]]:
    scorer = search.scorer
    st, nominal = model.fit.structure, scorer.nominal.structure.taus
    if not nominal or st.taus_held or len(st.taus) != len(nominal):
        return model, []
    aim = scorer.aim(model)
    held_st = replace(st, taus=nominal, taus_held=True)
    fit = scorer.polish(model.flow, held_st, model.delay_free, aim)  # only a free dead time moves
    held = scorer.model(model.by_slot(), fit, model.delay_free, model.flow, target=aim.y)
    trading = {a.name for a in model.active if search.fitter.trades_with_prior(a.candidate)}
    held = search.validated(search.rerefine(held, only=trading) if trading else held)
    kept, delta = _decide(search, model, held, scorer.prior_penalty(st))
    order = np.argsort(st.taus)  # both ascending: the i-th fitted time constant is the i-th nominal one's
    return kept, [LinearMove(parameter="time_constant", index=i, nominal=float(nominal[i]),
                             proposed=float(st.taus[order[i]]), moved=kept is model, delta_bic=delta,
                             fit_held=held.heldout, fit_moved=model.heldout) for i in range(len(nominal))]


def _settle_gain(search: Search, model: Model) -> tuple[Model, list[LinearMove]]:
    scorer, p = search.scorer, search.scorer.p
    nom = scorer.nominal
    k_nom = nominal_gain(nom.num, nom.den)
    fit = model.fit
    k_fit = fit.gain * p.y_scale
    if not np.isfinite(k_nom) or k_nom == 0.0 or fit.structure.gain is not None:
        return model, []
    aim = scorer.aim(model)
    held_st = replace(fit.structure, gain=k_nom / p.y_scale)
    held_fit = fit_one(model.flow, aim.y, p.train, held_st, p.dt, prefilter=scorer.lam)
    held = scorer.model(model.by_slot(), held_fit, model.delay_free, model.flow, target=aim.y)
    penalty = ((np.log(k_fit / k_nom) / PRIOR_WIDTH) ** 2) if k_fit * k_nom > 0 else np.inf
    late = late_start(model) is not None
    if held.bic - (model.bic + penalty) >= DELTA_BIC:   # the move could count: the findings around the held gain
        held = search.rerefine(held)
        if late:   # and a late valve searched again there, not only refined from the moved gain's band
            held = late_afresh(search.fitter, held)
    held = search.validated(held)
    kept, delta = _decide(search, model, held, float(penalty), under_load=late)
    return kept, [LinearMove(parameter="gain", index=None, nominal=k_nom, proposed=k_fit, moved=kept is model,
                             delta_bic=delta, fit_held=held.heldout, fit_moved=model.heldout)]


def _settle_held_integrator(search: Search, model: Model) -> tuple[Model, list[LinearMove]]:
    """A held integrating plant (:func:`~valve_emulator.diagnosis.explain.pipeline.held_integrator`): the final
    chain with the time constants and the gain freed together, against ``model`` (held), by :func:`_decide`
    with the drifting-load noise model's condition — the rule of a gain move beside a late finding, for the
    same reason: a free-run fit around a wandering load shrinks the gain to replay less of it."""
    scorer, p = search.scorer, search.scorer.p
    st = model.fit.structure
    k_nom = float(st.gain) * p.y_scale
    aim = scorer.aim(model)
    free = scorer.polish(model.flow, replace(st, taus_held=False, gain=None), model.delay_free, aim)
    moved = search.validated(scorer.model(model.by_slot(), free, model.delay_free, model.flow, target=aim.y))
    k_fit = moved.fit.gain * p.y_scale
    penalty = scorer.prior_penalty(moved.fit.structure) + (
        ((np.log(k_fit / k_nom) / PRIOR_WIDTH) ** 2) if k_fit * k_nom > 0 else np.inf)
    kept, delta = _decide(search, moved, model, float(penalty), under_load=True)
    fitted = moved.fit.structure.taus
    out = [LinearMove(parameter="gain", index=None, nominal=k_nom, proposed=k_fit, moved=kept is moved,
                      delta_bic=delta, fit_held=model.heldout, fit_moved=moved.heldout)]
    out += [LinearMove(parameter="time_constant", index=i, nominal=float(t), proposed=float(f), moved=kept is moved,
                       delta_bic=delta, fit_held=model.heldout, fit_moved=moved.heldout)
            for i, (t, f) in enumerate(zip(sorted(st.taus), sorted(fitted)))]
    return kept, out


def settle(search: Search, model: Model) -> tuple[Model, tuple[LinearMove, ...]]:
    """The final model with the nominal linear part held where the data do not demand a move, and the tests
    (see the module docstring). Without a nominal model there is no prior: ``model`` and ``()``."""
    if not search.scorer.nominal.given:
        return model, ()
    model = search.validated(model)
    if search.held_integrator:
        model, moves = _settle_held_integrator(search, model)
        return model, tuple(moves)
    model, poles = _settle_poles(search, model)
    model, gain = _settle_gain(search, model)
    return model, tuple(gain + poles)


def dead_time_move(findings: tuple[Finding, ...], nominal_delay: float, delay: float) -> tuple[LinearMove, ...]:
    """The ``dead_time`` finding, if any, as a move of the linear part's dead time (its test is the finding's)."""
    return tuple(LinearMove(parameter="dead_time", index=None, nominal=nominal_delay, proposed=delay, moved=True,
                            delta_bic=f.delta_bic, fit_held=f.fit_without, fit_moved=f.fit_with)
                 for f in findings if f.physics == "dead_time")
