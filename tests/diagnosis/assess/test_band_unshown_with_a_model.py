"""With a nominal model, a stiction call goes through the rule plant data's calls go through: a valve band OP
hardly crosses, on a loop that does not cycle, that the record does not show (``decision.band_unshown``) is no
call but ``cannot_tell``, naming the sticky valve and the healthy one; a sticky loop that cycles keeps its call.

Known truth: loops of the independent simulator (tests/unseen_loops.py), each diagnosed with the nominal model its
family hands out. Measured (2026-11-27) over the with-model draws of the shared sets (132): stiction calls on
healthy valves 14 → 7 (healthy level loops 4 → 2, coarse A/D 5 → 0; slow noisy valves 4 and a healthy flow loop
1 stay: they cycle or OP crosses their band), right calls on sticky valves 70 → 67 (three late onsets, weak calls,
whose band OP's swings hardly cross from the onset found on), strong calls unchanged (23, all right).
Since 2026-11-28 a call the drifting-load alternative explains at least as well is contested too
(``decision.MODEL_CONTEST_BIC``, docs/diagnosis.md *With a model, the drifting-load contest*): the slow noisy
valves and the healthy flow loop left above are ``cannot_tell``; the with-model draws then have 2 stiction calls
on 66 healthy valves and 95 of 106 sticky valves found.

Slow: the draws are shared with the other property tests (one diagnosis each per run).
"""

from __future__ import annotations

import pytest
from unseen_loops import ALL, Draw, diagnosed, diagnosed_all

from valve_emulator.diagnosis.answers import VALVE_FRICTION

pytestmark = pytest.mark.slow

WITH_MODEL = [k for k in ALL if k.mode == "model"]
#: A level loop with a healthy valve and its exact nominal model whose weak stiction call the rule takes back: it
#: does not cycle, OP's swings cross the band found (S 3.02 %, J 2.34 %) in 2 % of them, and the record does not
#: show it (OP's moves inside it reach PV: ΔBIC 57 under a drifting-load noise model). Until 2026-11-28 the example
#: was 2032.7.5, whose held integrating plant (docs/diagnosis.md, *A level loop's model is held*) now finds no band
#: there at all: it is answered ``no_stiction``.
HEALTHY_UNSHOWN = [Draw("healthy_level", (2032, 7, 2), "model")]
#: The second such loop of the rule's measurement: its band was a deadband "from t ≈ 1387 s on", an onset that
#: neither counted against the deadband acting throughout nor showed a healthy valve before it; since a located
#: onset must be evidenced (``Search.onset_evidenced``, 2026-11-27) no valve is left to take back.
HEALTHY_NO_ONSET = Draw("healthy_level", (2032, 7, 1), "model")
#: A sticky level loop in a limit cycle (regularity above 1), with its nominal model.
STICKY_CYCLING = Draw("level_sticky", (7, 0, 4), "model")
HEALTHY_FAMILIES = ("healthy_level", "coarse_ad", "slow_noisy_valve", "healthy_flow", "aggressive_pi")


def _taken_back(doc: dict) -> bool:
    return doc["answer"] == "cannot_tell" and any("healthy valve fits too" in r["sentence"] for r in doc["reasons"])


@pytest.mark.parametrize("key", HEALTHY_UNSHOWN, ids=lambda d: d.name)
def test_a_healthy_valve_whose_band_the_record_does_not_show_is_cannot_tell_naming_both_with_a_model(key):
    doc = diagnosed(key).doc
    assert _taken_back(doc), doc["verdict"]
    codes = [r["code"] for r in doc["reasons"]]
    assert codes[0] in VALVE_FRICTION and "weak_evidence" in codes, doc["reasons"]
    claimed = "a valve with a deadband (" if codes[0] == "deadband" else "a sticky valve ("
    assert doc["reasons"][0]["sentence"].startswith(claimed) and claimed in doc["verdict"], doc["reasons"]
    assert not any(f["physics"] in VALVE_FRICTION for f in doc["findings"])
    assert doc["friction"] is None and doc["strength"] is None
    assert "cannot tell" in doc["verdict"]


def test_a_healthy_valve_whose_late_band_the_record_does_not_evidence_is_no_stiction_with_a_model():
    doc = diagnosed(HEALTHY_NO_ONSET).doc
    assert doc["answer"] == "no_stiction", doc["verdict"]
    assert not any(f["physics"] in VALVE_FRICTION for f in doc["findings"]) and doc["friction"] is None


def test_a_sticky_loop_that_cycles_keeps_its_stiction_call_with_a_model():
    doc = diagnosed(STICKY_CYCLING).doc
    assert doc["oscillation"]["oscillating"]
    assert doc["answer"] == "stiction" and doc["strength"] is not None
    assert any(f["physics"] in VALVE_FRICTION for f in doc["findings"]) and doc["friction"] is not None


def test_no_loop_that_cycles_has_its_call_taken_back_with_a_model():
    cycling = [d.draw.name for d in diagnosed_all(WITH_MODEL)
               if d.doc["oscillation"]["oscillating"] and _taken_back(d.doc)]
    assert not cycling, cycling


def test_with_a_model_healthy_valves_are_called_stiction_half_as_often_and_sticky_ones_keep_their_calls():
    """Measured: 7 calls of 46 healthy loops (14 before the rule), 67 of 86 sticky loops (70 before)."""
    docs = diagnosed_all(WITH_MODEL)
    healthy = [d for d in docs if d.draw.family in HEALTHY_FAMILIES]
    sticky = [d for d in docs if d.draw.family not in HEALTHY_FAMILIES]
    wrong = [d.draw.name for d in healthy if d.doc["answer"] == "stiction"]
    right = [d.draw.name for d in sticky if d.doc["answer"] == "stiction"]
    assert len(wrong) <= 8, wrong
    assert len(right) >= 66, f"{len(right)} of {len(sticky)} sticky loops answered stiction"
    assert sum(_taken_back(d.doc) for d in healthy) >= 6
