"""Every answer carries an oscillation summary and one recommended action an engineer can act on."""

from __future__ import annotations

import numpy as np
import pytest

from valve_emulator.diagnosis.answers import Answer, Reason
from valve_emulator.diagnosis.assess.action import TARGET_GAIN_MARGIN, recommend
from valve_emulator.diagnosis.assess.adequacy import Cycle, cycle
from valve_emulator.diagnosis.candidates.tuning import TuningAssessment
from valve_emulator.recordings.recording import Recording

RNG = np.random.default_rng(11)
CYCLE = Cycle(True, 4.0, 60.0, 1.5, 3.0, "PV")
QUIET = Cycle(False, 0.4, float("nan"))


def _loop(pv_amp: float, op_amp: float, period: float, noise: float = 0.02, n: int = 3000) -> Recording:
    t = np.arange(n, dtype=float)
    op = 50.0 + op_amp * np.sin(2 * np.pi * t / period) + noise * RNG.normal(size=n)
    pv = 20.0 + pv_amp * np.sin(2 * np.pi * t / period - 1.0) + noise * RNG.normal(size=n)
    return Recording(t=t, sp=None, op=op, mv=None, pv=pv, source="sine")


def test_a_regular_cycle_is_summarised_by_its_period_and_the_swings_of_pv_and_op():
    c = cycle(_loop(pv_amp=2.0, op_amp=5.0, period=80.0))
    assert c.oscillating and c.regularity > 1.0
    assert c.period == pytest.approx(80.0, rel=0.05)
    assert c.pv_amplitude == pytest.approx(2.0, rel=0.05) and c.op_amplitude == pytest.approx(5.0, rel=0.05)
    assert c.words.startswith("oscillation: period 80") and c.to_json()["period"] == pytest.approx(c.period)


def test_noise_alone_is_no_oscillation_and_says_so():
    n = 3000
    rec = Recording(t=np.arange(n, dtype=float), sp=None, op=50 + RNG.normal(size=n), mv=None,
                    pv=RNG.normal(size=n), source="noise")
    c = cycle(rec)
    assert not c.oscillating and c.words.startswith("no oscillation")
    assert c.to_json()["period"] is None and c.to_json()["pv_amplitude"] is None


def test_a_sticky_valve_is_stroke_tested_with_its_s_and_j():
    a = recommend(Answer.STICTION, "stiction", (Reason.STICTION,), CYCLE, friction="S ≈ 3 % travel; J ≈ 1 % travel")
    assert a.code == "stroke_test_valve" and "S ≈ 3 % travel" in a.words and "positioner" in a.words


def test_an_aggressive_loop_is_retuned_with_a_gain_that_gives_the_target_gain_margin():
    tuning = TuningAssessment(judged=True, aggressive=True, kc=2.0, ti=10.0, gain_margin=1.25)
    a = recommend(Answer.NO_STICTION, "tuning", (Reason.TUNING,), CYCLE, tuning=tuning)
    assert a.code == "retune"
    assert f"Kc ≈ {2.0 * 1.25 / TARGET_GAIN_MARGIN:.3g}" in a.words and "Ti = 10 s" in a.words


def test_a_cycle_the_loop_does_not_make_is_looked_for_upstream_at_its_period():
    for cause in ("disturbance", "linear"):
        a = recommend(Answer.NO_STICTION, cause, (), CYCLE)
        assert a.code == "find_upstream_source" and "60 s" in a.words


@pytest.mark.parametrize("answer, cause, codes, code", [
    (Answer.NO_RESPONSE, "", (Reason.NO_RESPONSE,), "inspect_loop"),
    (Answer.CANNOT_TELL, "", (Reason.FLAT_PV,), "check_transmitter"),
    (Answer.CANNOT_TELL, "", (Reason.STICTION, Reason.WEAK_EVIDENCE), "stroke_test_valve"),
    (Answer.CANNOT_TELL, "", (Reason.NO_EXCITATION,), "collect_data"),
    (Answer.CANNOT_TELL, "", (Reason.TUNING, Reason.LIMIT_CYCLE), "stroke_test_valve"),
    (Answer.NO_STICTION, "quantization", (Reason.QUANTIZATION,), "check_transmitter"),
    (Answer.NO_STICTION, "linear", (Reason.LINEAR,), "none"),
])
def test_each_answer_gets_its_action(answer, cause, codes, code):
    assert recommend(answer, cause, codes, QUIET).code == code
