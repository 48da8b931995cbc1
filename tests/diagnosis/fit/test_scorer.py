"""The scorer's bookkeeping: the samples every model is scored on, what BIC counts, the prior between pole sets
and the dead times searched near a value."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from first_order_staircase import NOMINAL, staircase_problem

from valve_emulator.diagnosis.candidates.base import Kind
from valve_emulator.diagnosis.fit.chain import Active
from valve_emulator.diagnosis.fit.cost import bic
from valve_emulator.diagnosis.fit.data import BURN_CAP, fit_percent, held_out_start, with_burn_in
from valve_emulator.diagnosis.fit.linear import PRIOR_WIDTH, LinearStructure, fit_one
from valve_emulator.diagnosis.fit.nominal import Nominal
from valve_emulator.diagnosis.fit.scorer import Scorer, library_burn_in

T = 1000


def _claims(n: int):
    """A candidate that claims ``n`` samples of burn-in (and records the window it was asked on)."""
    asked = []
    return SimpleNamespace(burn_in=lambda ctx: asked.append(ctx.window) or n, asked=asked)


def test_the_fit_part_starts_after_the_longest_burn_in_a_candidate_claims():
    problem = staircase_problem(T)
    w0, w1 = problem.train
    assert w1 == held_out_start(T)
    short, long_ = _claims(w0 - 10), _claims(w0 + 100)
    burn = library_burn_in(problem, NOMINAL, {"a": short, "b": long_})
    assert burn == w0 + 100 and short.asked == [(w0, w1)]
    later = with_burn_in(problem, burn)
    assert later.train == (w0 + 100, w1) and later.y is problem.y   # the scaling is the prepared one
    assert with_burn_in(problem, w0 - 10) is problem


def test_a_burn_in_claim_is_capped_at_a_fixed_share_of_the_record():
    problem = staircase_problem(T)
    assert with_burn_in(problem, T).train == (int(BURN_CAP * T), problem.train[1])


def test_bic_counts_the_linear_part_a_free_dead_time_and_each_candidates_parameters_once():
    problem = staircase_problem(T)
    scorer = Scorer(problem, NOMINAL, {})
    flow = problem.op.copy()
    fit = fit_one(flow, problem.y, problem.train, NOMINAL.structure, problem.dt)
    held = scorer.model({}, fit, False, flow, target=problem.y)
    assert held.k == fit.structure.n_params()
    assert held.bic == bic(fit.sse, fit.n, held.k)
    assert held.heldout == fit_percent(problem.y[problem.test[0]:], held.y_hat[problem.test[0]:]) > 90.0
    valve = Active(SimpleNamespace(name="stiction", slot="valve", kind=Kind.CHAIN, n_params=3), np.zeros(3))
    dead_time = Active(SimpleNamespace(name="dead_time", slot="delay", kind=Kind.DELAY, n_params=1), np.zeros(1))
    freed = scorer.model({"valve": valve, "delay": dead_time}, fit, True, flow, target=problem.y)
    assert freed.k == held.k + 1 + 3     # the dead time once (as freed), the valve's three parameters
    assert freed.by_slot()["delay"].params.tolist() == [fit.structure.delay]   # the fitted dead time


def test_the_prior_between_pole_sets_is_the_squared_log_distance_to_the_nominal_poles_in_widths():
    scorer = Scorer(staircase_problem(T), NOMINAL, {})
    assert scorer.prior_penalty(LinearStructure(taus=(10.0 * np.exp(2 * PRIOR_WIDTH),))) == pytest.approx(4.0)
    assert scorer.prior_penalty(LinearStructure(taus=(10.0,))) == 0.0
    assert scorer.prior_penalty(LinearStructure(taus=(5.0, 10.0))) == 0.0   # another order: not comparable
    identified = Nominal(structure=NOMINAL.structure, given=False)
    assert Scorer(staircase_problem(T), identified, {}).prior_penalty(LinearStructure(taus=(40.0,))) == 0.0


def test_dead_times_near_a_value_stay_on_the_problems_grid():
    problem = staircase_problem(T)
    scorer = Scorer(problem, NOMINAL, {})
    lo, hi = int(problem.delays.min()), int(problem.delays.max())
    assert scorer.near(3.0, 2).tolist() == [max(lo, 1), 2, 3, 4, 5]
    assert scorer.near(float(hi), 3).max() == hi and scorer.near(0.0, 3).min() == lo


def test_jobs_the_linear_fit_cannot_tell_apart_are_scored_once_with_the_numbers_of_each_alone(monkeypatch):
    problem = staircase_problem(T)
    scorer = Scorer(problem, NOMINAL, {})
    aim = scorer.aim(None)
    rng = np.random.default_rng(5)
    flows = problem.op[:, None] + rng.normal(0.0, 2.0, (T, 70))
    delays = np.arange(0, 5)
    first_order = LinearStructure(taus=(10.0,), delay=2.0)
    # The same poles with another bound and dead time: the same job on a grid of dead times. A held gain is
    # a job of its own (a grid at a held gain is fitted at that gain, input_grid_sse).
    same = LinearStructure(taus=(10.0,), delay=4.0, min_tau=0.5)
    jobs = [(first_order, delays), (LinearStructure(integrating=True), delays), (same, delays.copy()),
            (first_order, None), (same, None), (LinearStructure(taus=(10.0,), delay=2.0, gain=1.5), None)]
    alone = [scorer.sse_flows_all(flows, [job], aim)[0] for job in jobs]
    calls = []
    sse_flows = scorer.sse_flows
    monkeypatch.setattr(scorer, "sse_flows", lambda *a, **kw: calls.append(a[1]) or sse_flows(*a, **kw))
    together = scorer.sse_flows_all(flows, jobs, aim)
    assert len(calls) == 5 * 2   # five distinct jobs (the dead time held is the structure's own), two chunks
    for (sse, used), (sse_alone, used_alone) in zip(together, alone):
        assert sse.tobytes() == sse_alone.tobytes() and np.array_equal(used, used_alone)
    assert not np.array_equal(together[3][0], together[4][0])   # own dead times 2 s and 4 s differ
