"""The nominal model as a prior: when a group of its linear part moves, and how a move is reported."""

from __future__ import annotations

from types import SimpleNamespace

from valve_emulator.diagnosis.explain.prior import _decide, dead_time_move, nominal_gain, settle
from valve_emulator.diagnosis.explain.result import Finding
from valve_emulator.diagnosis.explain.search import DELTA_BIC, DELTA_FIT


def _model(bic: float, heldout: float = 0.0) -> SimpleNamespace:
    return SimpleNamespace(bic=bic, heldout=heldout)


def test_the_nominal_values_are_kept_unless_moving_them_lowers_the_penalised_bic_by_the_threshold():
    moved = _model(100.0, heldout=90.0)
    kept, delta = _decide(None, moved, _model(100.0 + 3.0 + DELTA_BIC, heldout=80.0), penalty=3.0)
    assert kept is moved and delta == DELTA_BIC
    held = _model(100.0 + 3.0 + DELTA_BIC - 0.01, heldout=80.0)
    kept, delta = _decide(None, moved, held, penalty=3.0)
    assert kept is held and delta < DELTA_BIC


def test_a_move_that_lowers_the_bic_a_lot_but_buys_no_held_out_fit_is_not_made():
    moved = _model(100.0, heldout=97.66)
    held = _model(100.0 + 38.0, heldout=97.64)   # ΔBIC 38 for 0.02 points: the nominal value stays
    kept, delta = _decide(None, moved, held, penalty=0.0)
    assert kept is held and delta == 38.0
    just = _model(100.0, heldout=97.64 + DELTA_FIT)
    assert _decide(None, just, held, penalty=0.0)[0] is just


def test_the_steady_state_gain_of_an_integrator_is_per_second():
    assert nominal_gain((2.0,), (10.0, 1.0)) == 2.0
    assert nominal_gain((0.5,), (8.0, 1.0, 0.0)) == 0.5   # 0.5/(s(8s+1)): the s drops out


def test_without_a_nominal_model_nothing_is_settled():
    search = SimpleNamespace(scorer=SimpleNamespace(nominal=SimpleNamespace(given=False)))
    model = _model(1.0)
    assert settle(search, model) == (model, ())


def test_a_dead_time_finding_is_reported_as_a_move_of_the_dead_time_with_its_own_test():
    found = (Finding(physics="stiction", parameters={}, windows=(), evidence="", description=""),
             Finding(physics="dead_time", parameters={}, windows=(), evidence="", description="", delta_bic=42.0,
                     fit_without=70.0, fit_with=80.0))
    (move,) = dead_time_move(found, nominal_delay=2.0, delay=3.5)
    assert (move.parameter, move.nominal, move.proposed, move.moved) == ("dead_time", 2.0, 3.5, True)
    assert (move.delta_bic, move.fit_held, move.fit_moved) == (42.0, 70.0, 80.0)
    assert dead_time_move(found[:1], 2.0, 2.0) == ()
