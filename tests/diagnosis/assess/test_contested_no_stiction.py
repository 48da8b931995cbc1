"""A "no stiction" answer that only a drifting-load noise model supports is no answer when a sticky valve, under
the same noise model, explains PV at least as well: it is "cannot tell", naming both the cause and the valve with
its band. A healthy loop whose cause explains PV clearly better than any valve the search tried keeps its answer.

Both recordings come from the independent closed-loop simulator (:mod:`valve_emulator.benchmark.independent`),
diagnosed as plant data (no model, OP in % travel); about 3 s each.
"""

from __future__ import annotations

import numpy as np
import pytest

import valve_emulator as ve
from valve_emulator.benchmark.independent import Controller, Load, Loop, Measurement, Plant, Valve, draw, simulate
from valve_emulator.diagnosis.answers import VALVE_FRICTION
from valve_emulator.diagnosis.assess.adequacy import op_swings, swings
from valve_emulator.diagnosis.assess.decision import MIN_FIT, NOISE_BANDS, band_crossings
from valve_emulator.diagnosis.explain import pipeline
from valve_emulator.diagnosis.explain.search import DELTA_BIC


def _diagnosed(rec):
    return ve.diagnose(rec, op_range=(0.0, 100.0))


def _rests_on_the_load_model(d) -> bool:
    """The final model predicts held-out PV worse than their mean, and only the drifting-load noise model says it
    explains PV."""
    e = d.explanation
    return e.fit_after < MIN_FIT and e.input_delta_bic >= DELTA_BIC


def _no_valve_that_matters(d) -> bool:
    band = NOISE_BANDS * d.assessment.op_noise
    return all(f.parameters["S"] < band for f in d.explanation.findings if f.physics in VALVE_FRICTION)


@pytest.fixture(scope="module")
def sticky_level_loop():
    """An integrating level loop behind a 9 s lag with a sticky valve (S ≈ 2.6 %) and a wandering load: its free run
    cannot follow the load, and without the valve the search names the tuning, while a deadband explains PV about
    as well under the drifting-load noise model (ΔBIC 8, below the 10 a call on it needs). (Draw 32.18, the example
    here before, is now called on its valve: PV shows the band's memory beyond any characteristic,
    ``test_valve_memory.py``.) Since the set point's bound on the dead time (``pipeline._setpoint_cap``) this draw
    is called on its valve too (its 99 s dead time searched again below 35 s): no drawn level loop is left
    contested, so the loop is diagnosed here as it was before that rule, the rule held off, to keep testing the
    contested answer on the record it was measured on."""
    rec, truth, _ = draw("level_sticky", np.random.default_rng([32, 9]))
    assert truth["sticky"]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "_setpoint_cap", lambda recording, searched: None)
        return _diagnosed(rec)


@pytest.fixture(scope="module")
def healthy_level_loop():
    """An integrating level loop with a healthy valve, a wandering load and an oscillating disturbance."""
    plant = Plant(kind="integrating_lag", gain=0.011, lag=2.4, delay=3.4, pv0=50.0)
    loop = Loop(plant=plant, valve=Valve(),
                controller=Controller(kc=4.2, ti=86.0, sp_steps=((300.0, 48.3), (1100.0, 51.0), (1900.0, 51.2))),
                load=(Load("random_walk", size=0.02), Load("sine", size=2.0, period=200.0)),
                measurement=Measurement(noise=0.05), dt=1.0, duration=2400.0, seed=2)
    rec, _ = simulate(loop)
    return _diagnosed(rec)


def test_a_sticky_valve_that_explains_pv_as_well_turns_no_stiction_into_cannot_tell(sticky_level_loop):
    d = sticky_level_loop
    assert _rests_on_the_load_model(d) and _no_valve_that_matters(d)
    alternative = d.explanation.valve_alternative
    assert alternative is not None and alternative.load_delta_bic > -DELTA_BIC
    assert str(d.answer) == "cannot_tell", d.verdict


def test_cannot_tell_names_both_the_cause_and_the_valve_with_its_band(sticky_level_loop):
    doc = sticky_level_loop.to_json()
    codes = [r["code"] for r in doc["reasons"]]
    valve = next(r for r in doc["reasons"] if r["code"] in VALVE_FRICTION)
    assert codes[0] not in VALVE_FRICTION and codes[0] not in ("not_explained", "weak_evidence"), codes
    assert "S ≈" in valve["sentence"] and "drifting-load" in valve["sentence"]
    assert doc["friction"] is None and doc["strength"] is None


def test_a_healthy_loop_whose_disturbance_explains_pv_better_than_any_valve_stays_no_stiction(healthy_level_loop):
    d = healthy_level_loop
    assert _rests_on_the_load_model(d)
    alternative = d.explanation.valve_alternative
    assert alternative is not None and alternative.load_delta_bic <= -DELTA_BIC
    assert str(d.answer) == "no_stiction" and d.cause == "disturbance", d.verdict


def _triangle(amplitude: float, period: int, cycles: int, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    k = np.arange(period * cycles)
    x = amplitude * (2.0 * np.abs(2.0 * ((k / period) % 1.0) - 1.0) - 1.0)
    return 50.0 + x + np.random.default_rng(seed).normal(0.0, noise, x.size)


def test_the_swings_of_a_noisy_triangle_are_its_peak_to_peak_travel():
    op = _triangle(2.0, 100, 12, noise=0.05)
    sw = op_swings(op)
    assert sw.size == 22   # 23 turns inside the record: the swings before the first and after the last are unknown
    assert np.all(np.abs(sw - 4.0) < 0.4), sw


def test_noise_inside_the_hysteresis_makes_no_turn():
    x = np.random.default_rng(1).uniform(-1.0, 1.0, 2000)
    assert swings(x, 2.5).size == 0
    assert swings(np.full(50, 3.0), 0.1).size == 0


def test_a_band_is_crossed_by_the_swings_larger_than_it_and_by_no_others():
    op = np.concatenate([_triangle(0.5, 40, 18, seed=2), _triangle(3.0, 200, 2, seed=3)])
    share = band_crossings(op, 2.0)   # the small swings are 1 wide, the large ones 6
    assert 0.05 < share < 0.2, share
    assert band_crossings(op, 0.5) > 0.95
    assert band_crossings(op, 7.0) == 0.0
