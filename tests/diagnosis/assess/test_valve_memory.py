"""A valve band's memory against any flow characteristic: a characteristic is a single-valued map of OP, friction is
hysteresis. Where the final model (no valve friction that could matter, a free run worse than PV's mean) rests on
something else, the valve the search tried and did not keep stands as a weak stiction call on a loop that does not
cycle regularly when PV shows the band's memory beyond any such map and OP's swings cross the band.

Checked on the statistic itself (known truth, an integrating plant driven through a backlash or through an
equal-percentage curve), on the decision (fast), and on the independent simulator: a sticky level loop whose
search kept an equal-percentage characteristic instead of the valve, and a healthy valve with a true
equal-percentage characteristic, which keeps it (slow: a few seconds each).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import valve_emulator as ve
from valve_emulator.benchmark.independent import Valve, draw, draw_loop, simulate
from valve_emulator.diagnosis.answers import VALVE_FRICTION, Answer, Reason
from valve_emulator.diagnosis.assess.adequacy import Adequacy
from valve_emulator.diagnosis.assess.decision import Decision, _valve_contest
from valve_emulator.diagnosis.explain.result import ValveAlternative
from valve_emulator.diagnosis.explain.search import DELTA_BIC
from valve_emulator.diagnosis.fit.frame import Frame
from valve_emulator.diagnosis.fit.linear import LinearStructure
from valve_emulator.diagnosis.fit.load_check import Memory, remembered

_BAND = 2.0
_PLANT = LinearStructure(integrating=True, delay=1.0)   # PV_k from flow up to k − 2, as _level makes it


def _backlash(op: np.ndarray, band: float) -> np.ndarray:
    """A valve that moves only when OP has crossed a band of ``band`` around it (a deadband)."""
    mv = np.empty_like(op)
    mv[0] = op[0]
    for k in range(1, op.size):
        gap = op[k] - mv[k - 1]
        mv[k] = mv[k - 1] if abs(gap) <= band / 2 else op[k] - np.sign(gap) * band / 2
    return mv


def _level(flow: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """An integrating plant (gain 0.05 per sample, two samples of dead time) under a random-walk load, measured
    with noise."""
    inflow = np.concatenate([np.zeros(2), flow[:-2] - flow.mean()])
    load = np.cumsum(rng.normal(0.0, 0.01, flow.size))
    return np.cumsum(0.05 * inflow) + load + rng.normal(0.0, 0.05, flow.size)


def _op(rng: np.random.Generator, n: int = 3000) -> np.ndarray:
    """OP wandering over 30–70 % with reversals of every size."""
    slow = np.cumsum(rng.normal(0.0, 0.6, n))
    slow = 30.0 + 40.0 * (slow - slow.min()) / np.ptp(slow)
    return slow + 3.0 * np.sin(np.arange(n) * 2 * np.pi / 90.0)


def test_a_level_driven_through_a_backlash_remembers_it_beyond_any_characteristic():
    rng = np.random.default_rng(11)
    op = _op(rng)
    mv = _backlash(op, _BAND)
    memory = remembered(_level(mv, rng), op, mv, _PLANT, 1.0, 100)
    assert memory.delta_bic >= DELTA_BIC, memory
    assert 0.7 < memory.share < 1.3, memory


def test_a_level_driven_through_an_equal_percentage_curve_shows_no_memory_a_band_could_claim():
    rng = np.random.default_rng(12)
    op = _op(rng)
    flow = 100.0 * 50.0 ** (op / 100.0 - 1.0)   # R = 50, no friction
    memory = remembered(_level(flow, rng), op, _backlash(op, _BAND), _PLANT, 1.0, 100)
    assert memory.delta_bic < DELTA_BIC, memory


def test_the_memory_does_not_depend_on_where_zero_is_or_on_the_scale_of_op_and_pv():
    rng = np.random.default_rng(13)
    op = _op(rng)
    mv = _backlash(op, _BAND)
    pv = _level(mv, rng)
    one = remembered(pv, op, mv, _PLANT, 1.0, 100)
    other = remembered(3.0 - 0.2 * pv, 250.0 - 4.0 * op, 250.0 - 4.0 * mv, _PLANT, 1.0, 100)
    assert other.delta_bic == pytest.approx(one.delta_bic, rel=1e-6, abs=1e-6)
    assert other.share == pytest.approx(one.share, rel=1e-6)


# -- the decision --------------------------------------------------------------------------------------------------

_NAMED = Decision(Answer.NO_STICTION, "characteristic", "an equal-percentage flow characteristic",
                  ((Reason.CHARACTERISTIC, "an equal-percentage flow characteristic"),))
_STILL = Adequacy(True, facts={"oscillating": False, "regularity": 0.6})


def _alternative(memory: Memory | None, load_delta_bic: float = 54.0) -> ValveAlternative:
    return ValveAlternative(physics="deadband", S=3.0, J=0.0, load_delta_bic=load_delta_bic,
                            intervals={"S": (1.0, 8.0), "J": (0.0, 20.0)}, memory=memory)


def _swinging_op(amplitude: float) -> np.ndarray:
    """OP turning every 40 samples by ``amplitude`` (its noise-free swings are that size)."""
    t = np.arange(2000)
    return 50.0 + amplitude / 2 * np.sign(np.sin(2 * np.pi * t / 80.0)) + np.random.default_rng(3).normal(0, 0.01,
                                                                                                           t.size)


def test_a_valve_whose_memory_pv_shows_and_whose_band_op_crosses_is_a_weak_call_without_a_regular_cycle():
    decided = _valve_contest(_NAMED, _alternative(Memory(150.0, 0.7)), Frame(), _STILL, _swinging_op(10.0))
    assert decided.answer is Answer.STICTION and decided.cause == "deadband"
    assert decided.S == 3.0 and decided.friction is not None
    assert Reason.WEAK_EVIDENCE in [code for code, _ in decided.reasons]
    assert "memory" in decided.reason and "cross the band" in decided.reason


@pytest.mark.parametrize("memory", [None, Memory(DELTA_BIC - 1.0, 0.7), Memory(150.0, -0.4)])
def test_without_memory_shown_with_the_valve_s_sign_the_record_stays_undecided(memory):
    decided = _valve_contest(_NAMED, _alternative(memory), Frame(), _STILL, _swinging_op(10.0))
    assert decided.answer is Answer.CANNOT_TELL and decided.friction is None


def test_a_band_op_hardly_crosses_leaves_the_record_undecided_whatever_its_memory():
    """On healthy level loops a band fitted to the controller's answers to a wandering load shows memory too, but OP
    hardly crosses it."""
    decided = _valve_contest(_NAMED, _alternative(Memory(900.0, 0.9)), Frame(), _STILL, _swinging_op(2.0))
    assert decided.answer is Answer.CANNOT_TELL


def test_a_valve_that_explains_pv_only_about_as_well_is_no_call_whatever_its_memory():
    decided = _valve_contest(_NAMED, _alternative(Memory(150.0, 0.7), load_delta_bic=DELTA_BIC - 1.0), Frame(),
                             _STILL, _swinging_op(10.0))
    assert decided.answer is Answer.CANNOT_TELL


# -- the independent simulator -------------------------------------------------------------------------------------

@pytest.mark.slow
def test_a_sticky_level_loop_whose_search_kept_a_characteristic_instead_is_called_on_its_valve():
    """Draw 32.18 of the level property test: an integrating plant, a sticky valve (S 2.89 %, J 2.12 %) that does not
    cycle regularly (r 0.70); the search kept an equal-percentage characteristic (R 29) and left a deadband of
    about 3.1 % that explains PV better under the drifting-load noise model."""
    rec, truth, _ = draw("level_sticky", np.random.default_rng([32, 18]))
    d = ve.diagnose(rec, op_range=(0.0, 100.0))
    doc = d.to_json()
    assert not d.assessment.adequacy.facts["oscillating"]
    assert doc["answer"] == "stiction" and doc["strength"] == "weak", d.verdict
    S = doc["friction"]["S"]
    assert abs(S["value"] / truth["S"] - 1.0) < 0.25 and S["interval"][0] <= truth["S"] <= S["interval"][1], S
    assert [f["physics"] for f in doc["findings"] if f["physics"] in VALVE_FRICTION] == [doc["friction"]["physics"]]
    assert "memory" in doc["reasons"][0]["sentence"]


@pytest.mark.slow
def test_a_healthy_valve_with_a_true_equal_percentage_characteristic_keeps_it():
    """A flow loop of the independent simulator under a sine load, its healthy valve given an equal-percentage
    characteristic (R 50): no stiction, and the characteristic found."""
    loop, _ = draw_loop("healthy_flow", np.random.default_rng([2032, 6, 0]))
    rec, _ = simulate(replace(loop, valve=Valve(characteristic="equal_percentage", rangeability=50.0)))
    doc = ve.diagnose(rec, op_range=(0.0, 100.0)).to_json()
    assert doc["answer"] == "no_stiction" and doc["friction"] is None
    found = {f["physics"]: f["parameters"] for f in doc["findings"]}
    assert found.get("characteristic", {}).get("type") == "equal_percentage", found
