"""Do the moves of OP that a valve band swallows reach PV? (``fit.load_check.swallowed``, read by the answer's
``decision.band_leaks``.)

A level (an integrating plant) under a random-walk load, fed through a valve that is either healthy or has a
dead band. The band the test is asked about is the same in both: OP's moves inside it reach PV when the valve is
healthy, and leave PV alone when the valve really holds them.
"""

from __future__ import annotations

import numpy as np
import pytest
from band_valve import level_through_band

from valve_emulator.diagnosis.assess.decision import _short_time_slope
from valve_emulator.diagnosis.explain.search import DELTA_BIC
from valve_emulator.diagnosis.fit.linear import LinearStructure
from valve_emulator.diagnosis.fit.load_check import swallowed

DT = 1.0
PLANT = LinearStructure(integrating=True, delay=2.0)


def _level(seed: int, healthy: bool, S: float = 3.0, n: int = 2000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The level's PV, OP and the claimed band's output (:func:`band_valve.level_through_band`, PV noise σ 0.05)."""
    return level_through_band(seed, healthy, S, n, DT)


@pytest.mark.parametrize("seed", range(5))
def test_the_moves_a_healthy_valve_passes_reach_pv_through_a_band_it_does_not_have(seed):
    pv, op, claimed = _level(seed, healthy=True)
    leak = swallowed(pv, op, claimed, PLANT, DT, start=50)
    assert leak.delta_bic >= DELTA_BIC and 0.5 < leak.share < 1.5, leak


@pytest.mark.parametrize("seed", range(5))
def test_the_moves_a_stuck_valve_holds_do_not_reach_pv(seed):
    pv, op, claimed = _level(seed, healthy=False)
    leak = swallowed(pv, op, claimed, PLANT, DT, start=50)
    assert leak.delta_bic < DELTA_BIC and abs(leak.share) < 0.2, leak


@pytest.mark.parametrize("seed", range(5))
def test_an_integrator_fitted_to_a_healthy_level_has_the_level_s_gain(seed):
    """Known truth: the level above rises 0.03 per unit of flow per second. Through an integrator, the regression of
    the leak test recovers that gain (the valve's coefficient, ``Swallowed.gain``), and a first-order plant that
    the search might take the level for — any τ long against the record's moves, with K = 0.03 τ — has that
    integrator as its short-time form (``decision._short_time_slope`` ≈ 1), while a flow loop's first-order plant
    (K 1, τ 2 s: initial slope 0.5) does not (a gain 17 times smaller than its slope)."""
    pv, op, claimed = _level(seed, healthy=True)
    leak = swallowed(pv, op, claimed, PLANT, DT, start=50)
    assert leak.gain == pytest.approx(0.03, rel=0.25), leak
    for tau in (50.0, 300.0):
        slope = _short_time_slope(leak.gain, {"gain": 0.03 * tau, "taus": [tau]})
        assert slope == pytest.approx(1.0, rel=0.25), (tau, slope)
    assert _short_time_slope(leak.gain, {"gain": 1.0, "taus": [2.0]}) is None
    assert _short_time_slope(leak.gain, {"gain": -0.03 * 100.0, "taus": [100.0]}) is None   # the other sign
    assert _short_time_slope(leak.gain, {"gain": 0.03, "taus": []}) is None   # an integrating plant has no τ


def test_the_short_time_slope_is_the_same_for_any_scale_of_op_and_pv():
    """The ratio is dimensionless: OP in other units (×50) and PV in other units (×0.2) give the same figure."""
    pv, op, claimed = _level(0, healthy=True)
    one = swallowed(pv, op, claimed, PLANT, DT, start=50)
    other = swallowed(0.2 * pv + 7.0, 50.0 * op - 3.0, 50.0 * claimed - 3.0, PLANT, DT, start=50)
    p_one, p_other = {"gain": 0.03 * 80.0, "taus": [80.0]}, {"gain": 0.2 * 0.03 * 80.0 / 50.0, "taus": [80.0]}
    assert _short_time_slope(other.gain, p_other) == pytest.approx(_short_time_slope(one.gain, p_one), rel=1e-6)
