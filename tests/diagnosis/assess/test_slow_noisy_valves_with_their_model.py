"""Slow noisy valves diagnosed with their nominal model are not called stiction.

Known truth: 20 loops of the independent simulator's ``slow_noisy_valve`` family (a self-regulating plant, an
actuator lag of 3–10 s, friction S of 0.2–0.6 % travel — below the 1 % that counts as stiction — and PV noise of
0.1–0.3; ``tests/unseen_loops.py: SLOW_NOISY_MODEL``, seed 15, used by no other set), each diagnosed with the
nominal model the family hands out (the plant exactly, the valve ideal and without lag). The nominal model leaves
out the lag and the small friction, and a band of 0.4–6 % (2–27 times the truth) bought fit in their place: 12 of
the 20 were weak stiction calls on main (2026-11-28). A call that a linear valve with a slowly drifting load
explains at least as well is no call (``decision.MODEL_CONTEST_BIC``, issue 32 §7): ``cannot_tell``, naming the
sticky valve and the drifting load. The rule was found on this set; the held-out check is
``bench/bench_unseen_loops.py --seed 0`` (docs/diagnosis.md). Slow: the draws are shared with the other property
tests (one diagnosis each per run).
"""

from __future__ import annotations

import pytest
from unseen_loops import SLOW_NOISY_MODEL, diagnosed_all

from valve_emulator.diagnosis.answers import VALVE_FRICTION

pytestmark = pytest.mark.slow


def test_nine_slow_noisy_valves_of_ten_are_not_called_stiction_with_their_model():
    """Measured 2026-11-28: 18 of 20 not stiction (12 of 20 stiction before the contest; the two left, 15.3.14
    and 15.3.18, are weak calls whose valve survives the drifting-load noise model by ΔBIC 10.8 and 9.7)."""
    docs = diagnosed_all(SLOW_NOISY_MODEL)
    assert all(d.truth["expected"] == "no_stiction" for d in docs)
    called = [d.draw.name for d in docs if d.doc["answer"] == "stiction"]
    assert len(called) <= 0.1 * len(docs), called


def test_a_band_the_drifting_load_explains_as_well_is_cannot_tell_naming_both():
    """Every call taken back names the valve (with its S) and what explains the record as well — the drifting load
    (the contest), or a healthy valve whose moves inside the band reach PV (``decision.band_leaks``, asked first) —
    keeps no friction finding and has no strength; and at least half the set is so answered (measured: 10 of 20,
    all by the contest; since the leak through the identified plant's short-time integrator, 2026-11-28, 9 by the
    contest and 15.3.15 by that leak, ΔBIC 23.3 where the contest's was 0.5)."""
    contested = [d for d in diagnosed_all(SLOW_NOISY_MODEL)
                 if d.doc["answer"] == "cannot_tell" and ("drifting load explains the record" in d.doc["verdict"]
                                                          or "a healthy valve answering" in d.doc["verdict"])]
    assert len(contested) >= 0.5 * len(SLOW_NOISY_MODEL), len(contested)
    for d in contested:
        doc = d.doc
        codes = [r["code"] for r in doc["reasons"]]
        assert codes[0] in VALVE_FRICTION and "weak_evidence" in codes, doc["reasons"]
        assert "S ≈" in doc["reasons"][0]["sentence"] and "either" in doc["verdict"], doc["verdict"]
        assert not any(f["physics"] in VALVE_FRICTION for f in doc["findings"]), d.draw.name
        assert doc["friction"] is None and doc["strength"] is None, d.draw.name
