"""A loop that cycles regularly, whose final model has no valve friction and predicts held-out PV worse than their
mean, and whose best valve the search tried explains PV better under the drifting-load noise model (ΔBIC ≥ 10),
is a weak stiction call resting on that valve, with its S, J and 95 % intervals; where the loop does not cycle,
or the valve explains PV only about as well, the answer stays "cannot tell", naming both.

The rule is checked on the decision itself (fast), and on a sticky level loop of the independent simulator whose
search did not keep the valve (slow: about 10 s).
"""

from __future__ import annotations

import numpy as np
import pytest

import valve_emulator as ve
from valve_emulator.benchmark.independent import draw
from valve_emulator.diagnosis.answers import VALVE_FRICTION, Answer, Reason
from valve_emulator.diagnosis.assess.adequacy import Adequacy
from valve_emulator.diagnosis.assess.decision import MIN_FIT, Decision, _valve_contest
from valve_emulator.diagnosis.explain.result import ValveAlternative
from valve_emulator.diagnosis.explain.search import DELTA_BIC
from valve_emulator.diagnosis.fit.frame import Frame

_TUNING = Decision(Answer.NO_STICTION, "tuning", "the loop cycles through its own controller",
                   ((Reason.TUNING, "the loop cycles through its own controller"),))


def _alternative(load_delta_bic: float) -> ValveAlternative:
    return ValveAlternative(physics="stiction", S=2.0, J=1.5, load_delta_bic=load_delta_bic,
                            intervals={"S": (1.6, 2.5), "J": (0.9, 2.4)})


def _facts(r: float) -> Adequacy:
    return Adequacy(True, facts={"oscillating": r > 1.0, "regularity": r})


def test_a_regular_cycle_with_a_valve_that_explains_pv_better_is_a_weak_stiction_call_on_that_valve():
    decided = _valve_contest(_TUNING, _alternative(60.0), Frame(), _facts(2.5))
    assert decided.answer is Answer.STICTION and decided.cause == "stiction"
    assert (decided.S, decided.J) == (2.0, 1.5)
    assert decided.intervals == {"S": (1.6, 2.5), "J": (0.9, 2.4)}
    assert Reason.WEAK_EVIDENCE in [code for code, _ in decided.reasons]
    assert decided.friction is not None and decided.friction.parameters == {"S": 2.0, "J": 1.5}
    assert decided.friction.intervals == decided.intervals and decided.friction.load_delta_bic == 60.0
    assert "regularly" in decided.reason and "did not keep" in decided.reason


def test_without_a_regular_cycle_the_same_valve_leaves_the_record_undecided():
    decided = _valve_contest(_TUNING, _alternative(60.0), Frame(), _facts(0.6))
    assert decided.answer is Answer.CANNOT_TELL and decided.friction is None and decided.S is None


def test_a_valve_that_explains_pv_only_about_as_well_leaves_a_cycling_loop_undecided():
    decided = _valve_contest(_TUNING, _alternative(DELTA_BIC - 2.0), Frame(), _facts(2.5))
    assert decided.answer is Answer.CANNOT_TELL and decided.friction is None


def test_a_valve_that_explains_pv_clearly_worse_leaves_the_cause_named():
    assert _valve_contest(_TUNING, _alternative(-3.0 * DELTA_BIC), Frame(), _facts(2.5)) is _TUNING


@pytest.fixture(scope="module")
def sticky_cycling_level_loop():
    """An integrating level loop behind a 9.5 s plant lag with a sticky valve (S 1.15 %, J 1.07 %) that cycles
    (regularity about 1.3): the search, judging held-out free-run fit, does not keep the valve."""
    rec, truth, _ = draw("level_sticky", np.random.default_rng([32, 30]))
    return ve.diagnose(rec, op_range=(0.0, 100.0)), truth


@pytest.mark.slow
def test_a_cycling_sticky_level_loop_the_search_left_without_a_valve_is_called_stiction_near_the_truth(
        sticky_cycling_level_loop):
    d, truth = sticky_cycling_level_loop
    e = d.explanation
    assert not any(f.physics in VALVE_FRICTION for f in e.findings), "the search itself kept a valve"
    assert e.fit_after < MIN_FIT and e.valve_alternative.load_delta_bic >= DELTA_BIC
    assert d.assessment.adequacy.facts["oscillating"]
    doc = d.to_json()
    assert doc["answer"] == "stiction" and doc["strength"] == "weak", d.verdict
    S = doc["friction"]["S"]
    assert abs(S["value"] / truth["S"] - 1.0) < 0.25, (S, truth["S"])
    assert S["interval"][0] <= truth["S"] <= S["interval"][1], (S, truth["S"])
    assert [f["physics"] for f in doc["findings"] if f["physics"] in VALVE_FRICTION] == [doc["friction"]["physics"]]
    assert "the search tried and did not keep" in d.report()   # the model below it is the search's, without it


@pytest.mark.slow
def test_the_twin_of_a_call_on_the_valve_the_search_left_sticks_and_replays_as_that_valve_fits(
        sticky_cycling_level_loop):
    """The answer rests on the valve the search tried and did not keep, so the twin is written from that option's
    model: its valve has the answer's band and jump, and its open-loop replay of the recorded OP is that model's
    free run (within 2 points of fit over the whole record), not the frictionless final model's."""
    from valve_emulator.diagnosis.fit.data import fit_percent
    from valve_emulator.simulation.replay import replay_op

    d, _ = sticky_cycling_level_loop
    twin = d.twin()
    friction = d.to_json()["friction"]
    for key in ("S", "J"):   # the JSON rounds to five significant figures
        assert abs(getattr(twin.config.valve, key) / friction[key]["value"] - 1.0) < 1e-4, (key, friction)
    pv = np.asarray(d.recording.pv, dtype=float)
    fitted = d.explanation.valve_alternative.fitted
    replayed = replay_op(twin.config, d.recording).pv
    assert abs(fit_percent(pv, replayed) - fit_percent(pv, fitted.predict(d.recording.op))) < 2.0
    assert "stiction found by the diagnosis" in "\n".join(twin.provenance)
