"""The fitter's choices between starts, variants and threshold values, on canned surfaces (no chain, no fit)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from valve_emulator.diagnosis.fit import fitter as fitter_module
from valve_emulator.diagnosis.fit.fitter import _FLAT, _STARTS, Fitter, Start
from valve_emulator.diagnosis.fit.linear import LinearStructure
from valve_emulator.diagnosis.fit.records import Model

NOMINAL_POLES = (10.0,)


def _fitter(*, given: bool = True, library: dict | None = None) -> Fitter:
    """A fitter whose scorer is a stub: a nominal model with one 10 s pole and ``library``."""
    scorer = SimpleNamespace(
        nominal=SimpleNamespace(given=given, structure=LinearStructure(taus=NOMINAL_POLES, delay=2.0)),
        library=library or {}, p=SimpleNamespace(n_fit=1000, dt=1.0))
    return Fitter(scorer)


def _start(score: float, tau: float) -> Start:
    return Start(score=score, params=np.array([score]), structure=LinearStructure(taus=(tau,), delay=2.0),
                 coarse=None)


def _model(delay_free: bool) -> Model:
    return Model(active=(), fit=None, delay_free=delay_free, k=1, bic=0.0, heldout=0.0, y_hat=np.zeros(1),
                 flow=np.zeros(1))


LAG = SimpleNamespace(name="actuator_lag", joint_with_poles=True, threshold_axes=())
STICTION = SimpleNamespace(name="stiction", joint_with_poles=False)


def test_the_best_starts_are_refined_in_order_of_their_score():
    starts = [_start(3.0, 20.0), _start(1.0, 5.0), _start(2.0, 7.0), _start(4.0, 10.0)]
    ranked = _fitter()._ranked(starts, STICTION)
    assert [s.score for s in ranked] == sorted(s.score for s in starts)[:_STARTS]


def test_a_lag_that_trades_with_the_poles_is_always_also_refined_from_the_nominal_poles():
    starts = [_start(3.0, 20.0), _start(1.0, 5.0), _start(2.0, 7.0), _start(4.0, 10.0), _start(5.0, 10.0)]
    ranked = _fitter()._ranked(starts, LAG)
    assert [s.score for s in ranked] == [1.0, 2.0, 4.0]   # the best start at the nominal poles, once
    # Without a nominal model there is no prior to choose between the two orderings of two lags.
    assert [s.score for s in _fitter(given=False)._ranked(starts, LAG)] == [1.0, 2.0]


def test_the_dead_time_is_freed_with_a_candidate_only_while_it_is_held_and_the_library_has_it():
    fitter = _fitter(library={"dead_time": SimpleNamespace(name="dead_time")})
    held = fitter.variants(_model(delay_free=False), STICTION)
    assert [(v.free, v.added) for v in held] == [(False, ("stiction",)), (True, ("stiction", "dead_time"))]
    assert [(v.free, v.added) for v in fitter.variants(_model(delay_free=True), STICTION)] == [(True, ("stiction",))]
    assert [v.free for v in _fitter().variants(_model(delay_free=False), STICTION)] == [False]


def test_a_threshold_moves_to_the_middle_of_the_flat_bottom_of_its_cost(monkeypatch):
    # The SSE is lowest at S = 2 (the bottom's edge), within the flat tolerance up to S = 5, and high beyond.
    n = 1000
    within = float(np.exp(0.9 * _FLAT / n))      # a cost N ln(SSE/SSE_min) just inside the flat bottom

    def sse_of(rows):
        s = rows[:, 0]
        return np.where(s == 2.0, 1.0, np.where((s > 2.0) & (s <= 5.0), within, 2.0))

    cand = SimpleNamespace(threshold_axes=(0,),
                           line=lambda ctx, best, axis: np.column_stack([np.arange(0.0, 8.01, 0.5),
                                                                          np.full(17, best[1])]))
    # Grid SSEs computed by ``sse_of(rows)`` in place of the chain and the linear kernel.
    monkeypatch.setattr(fitter_module, "sse_jobs_many", lambda requests: [
        [(sse_of(rows)[:, None], np.array([2]))] * len(jobs) for _scorer, _a, _c, _cand, rows, jobs, _aim in requests])
    best = _fitter().centre({}, None, cand, np.array([6.0, 1.5]), None, None)
    assert best.tolist() == [3.5, 1.5]
