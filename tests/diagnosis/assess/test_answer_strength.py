"""One answer, with its confidence: on loops of the independent simulator (known truth, not the search's model),
with and without a nominal model, the stiction calls marked strong are right in at least 95 %; and every document
of every drawn loop the property tests judge (tests/unseen_loops.py: about 250 diagnoses) agrees with itself —
its answer with its findings, its strength with its answer — and carries its oscillation summary and action.

Slow: each draw is diagnosed once per test run and shared with the other property tests (tests/unseen_loops.py),
about 2–3 s a diagnosis on one core. The calibration's set (``STRENGTH``): the sticky families (where calls are
made) drawn 22 times, the others (where a wrong strong call would come from) 6 times, each with and without the
model: enough for 95 % of the strong calls to mean something (at least 40 of them).
"""

from __future__ import annotations

import jsonschema
import pytest
from unseen_loops import ALL, HEALTHY_LEVEL, HEALTHY_LEVEL_MORE, STRENGTH, diagnosed, diagnosed_all

from valve_emulator.diagnosis.answers import VALVE_FRICTION
from valve_emulator.diagnosis.report.schema import schema

pytestmark = pytest.mark.slow
#: Strong calls the calibration needs before its rate means anything.
MIN_STRONG = 40
#: Every healthy level loop drawn, as plant data (8 of ``HEALTHY_LEVEL``, 24 more with another seed).
HEALTHY_LEVEL_AS_PLANT_DATA = [k for k in HEALTHY_LEVEL if k.mode == "plant"] + HEALTHY_LEVEL_MORE
_EACH = pytest.mark.parametrize("key", ALL, ids=lambda d: d.name)


@_EACH
def test_a_stiction_answer_has_a_strength_and_no_other_answer_has_one(key):
    doc = diagnosed(key).doc
    assert (doc["strength"] is not None) == (doc["answer"] == "stiction"), doc["verdict"]


@_EACH
def test_the_answer_and_the_findings_agree(key):
    doc = diagnosed(key).doc
    friction = [f for f in doc["findings"] if f["physics"] in VALVE_FRICTION]
    stiction = doc["answer"] == "stiction"
    assert bool(friction) == stiction and (doc["friction"] is not None) == stiction, doc["verdict"]


@_EACH
def test_the_document_is_valid_and_carries_its_oscillation_and_action(key):
    doc = diagnosed(key).doc
    jsonschema.Draft202012Validator(schema()).validate(doc)
    assert doc["action"]["words"] and doc["oscillation"]["words"]
    if doc["oscillation"]["oscillating"]:
        assert doc["oscillation"]["period"] > 0 and doc["oscillation"]["pv_amplitude"] > 0


def test_stiction_calls_marked_strong_are_right_in_at_least_95_percent():
    """Over the calibration's set and every healthy level loop drawn (where a wrong call would come from: a
    healthy level loop is still answered stiction, weak, see below)."""
    keys = STRENGTH + HEALTHY_LEVEL + HEALTHY_LEVEL_MORE
    strong = [(d.doc["answer"] == d.truth["expected"], d.draw.name, d.doc["verdict"])
              for d in diagnosed_all(keys) if d.doc["strength"] == "strong"]
    right = sum(ok for ok, _, _ in strong)
    wrong = [(name, verdict) for ok, name, verdict in strong if not ok]
    assert right >= 0.95 * len(strong), f"{right}/{len(strong)} strong calls right; wrong: {wrong}"
    assert len(strong) >= MIN_STRONG, f"{right}/{len(strong)} strong calls right, fewer than {MIN_STRONG}"


def test_a_level_loop_with_a_healthy_valve_gets_no_strong_stiction_call():
    """The calibration's set above has no healthy level loop. On these a PI on an integrating plant under a
    wandering load rings without friction, and a valve band that lets OP's small reversals pass without moving
    PV fits the load's drift: every one was called stiction as plant data, 10 of the 16 strong, before a strong
    call asked for a regular oscillation (``decision.cycling``). Of the 24 more drawn with another seed, one
    (7.7.16) is called strong: its wandering load makes a regular oscillation (r 2.53); it counts in the
    calibration above."""
    strong = [d.draw.name for d in diagnosed_all(HEALTHY_LEVEL) if d.doc["strength"] == "strong"]
    assert not strong, f"strong stiction calls on healthy level loops: {strong}"


def test_a_level_loop_with_a_healthy_valve_is_not_answered_stiction_as_plant_data_in_nine_of_ten():
    """32 healthy level loops as plant data (8 of ``HEALTHY_LEVEL``, 24 more with another seed). Measured
    2026-11-28: 1 of 32 answered stiction, 7.7.16, which oscillates regularly (3 before the swallowed moves were
    asked through the identified plant's short-time integrator, ``decision._short_time_slope``: 7.7.2 and 7.7.9;
    6 before a call whose band the record does not show became 'cannot tell' on the interval and too-short signs
    too, ``decision.band_unshown``; 21 before the leak). The floor is the measured figure. About 5 s a diagnosis
    (the 24 are read by this test only)."""
    keys = HEALTHY_LEVEL_AS_PLANT_DATA
    called = [d.draw.name for d in diagnosed_all(keys) if d.doc["answer"] == "stiction"]
    assert len(called) <= 0.1 * len(keys), f"{len(called)} of {len(keys)} answered stiction: {called}"
    assert len(called) <= 1, f"{len(called)} of {len(keys)} answered stiction (measured 1): {called}"



def _rests_on_a_valve_the_search_left(doc: dict) -> bool:
    """Whether a stiction answer rests on the valve the search tried and did not keep (its reasons say so)."""
    return any("search did not keep the valve" in r["sentence"] for r in doc["reasons"])


def test_a_healthy_level_loop_that_does_not_oscillate_regularly_is_never_called_on_a_valve_the_search_left():
    """A call may rest on the valve the search tried and did not keep only where the loop cycles regularly, as a
    sticky valve's limit cycle does (``decision._cycling_valve``). Of the 32 healthy level loops one cycles
    (7.7.16, called stiction by the search itself); on the others a valve alternative that explains PV better
    under the drifting-load model (ΔBIC up to 41 on them) makes no call."""
    left = [d.draw.name for d in diagnosed_all(HEALTHY_LEVEL_AS_PLANT_DATA) if d.doc["answer"] == "stiction"
            and not d.doc["oscillation"]["oscillating"] and _rests_on_a_valve_the_search_left(d.doc)]
    assert not left, f"healthy level loops without a regular cycle called on a valve the search left: {left}"

def test_a_band_op_hardly_crosses_that_the_record_does_not_show_is_cannot_tell_naming_both():
    """Where a healthy level loop's call was taken back, the answer names the sticky valve and the healthy one, and
    says why: OP hardly crosses the band, and the record does not show the band (OP's moves inside it reach PV,
    the friction acts on too short a stretch to ask, or the band's interval reaches into OP's noise)."""
    keys = HEALTHY_LEVEL_AS_PLANT_DATA
    taken = [d for d in diagnosed_all(keys) if d.doc["answer"] == "cannot_tell"
             and any("cross the band" in r["sentence"] for r in d.doc["reasons"])]
    assert len(taken) >= 20, f"{len(taken)} calls taken back"   # measured 2026-11-28 (18 before the short-time leak)
    for d in taken:
        codes = [r["code"] for r in d.doc["reasons"]]
        assert codes[0] in VALVE_FRICTION and "weak_evidence" in codes, (d.draw.name, d.doc["reasons"])
    signs = ("reach PV", "too short a stretch", "no band at all")
    unsigned = [d.draw.name for d in taken
                if not any(sign in r["sentence"] for r in d.doc["reasons"] for sign in signs)]
    assert not unsigned, f"taken back without saying why: {unsigned}"


def test_no_healthy_level_loop_that_does_not_oscillate_regularly_is_called_stiction_as_plant_data():
    """Of the 32, the two left called stiction without a regular oscillation (7.7.2, 7.7.9: bands OP hardly crosses,
    the qualifier said so) are ``cannot tell`` since their swallowed moves were asked through the identified
    first-order plant's short-time integrator (2026-11-28): where such a call is made, the reasons say OP hardly
    crosses the band; none is left."""
    keys = HEALTHY_LEVEL_AS_PLANT_DATA
    calls = [d.draw.name for d in diagnosed_all(keys)
             if d.doc["answer"] == "stiction" and not d.doc["oscillation"]["oscillating"]]
    assert not calls, f"healthy level loops without a regular cycle called stiction: {calls}"
