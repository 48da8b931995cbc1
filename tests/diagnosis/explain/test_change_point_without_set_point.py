"""Without a recorded set point, a loop that cycles from its first sample has no onset, however slow its cycle."""

from __future__ import annotations

import numpy as np

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis.explain.onset import suspect_onset
from valve_emulator.diagnosis.explain.pipeline import explain


def _concentration_loop(samples: int):
    """The proof cases' concentration loop (S = 5 %, J = 2 % from the first sample, no set point recorded)."""
    case = CASES[0]
    assert case.truth == {"stiction": {"S": 5.0, "J": 2.0}}
    rec, nominal, _ = generate(case, duration=samples - 1 + case.cut)
    assert not np.isfinite(np.asarray(rec.sp, dtype=float)).any()
    return rec, nominal


def test_a_first_cycle_slower_than_a_tenth_of_the_record_is_no_onset():
    """At 1,000 samples the loop's cycle (about 230 s) outlasts a tenth of the record; its first low dwell,
    longer than the later ones, must not read as a quiet stretch before a change."""
    rec, _ = _concentration_loop(1000)
    assert suspect_onset(np.asarray(rec.pv, dtype=float), None) is None


def test_a_valve_sticking_from_the_first_sample_is_answered_without_an_onset_and_its_j_kept():
    rec, nominal = _concentration_loop(1000)
    found = explain(rec, nominal)
    stiction = next(f for f in found.findings if f.physics == "stiction")
    assert stiction.onset is None and "onset_s" not in stiction.parameters
    assert abs(stiction.parameters["S"] - 5.0) < 0.25 and abs(stiction.parameters["J"] - 2.0) < 0.2


def test_a_loop_that_starts_to_cycle_late_is_still_located_without_a_set_point():
    """A quiet regulating loop that starts a slow stick-slip cycle (period 240 samples) at sample 1,200 of 3,000."""
    rng = np.random.default_rng(5)
    k = np.arange(3000)
    cycle = np.where(k >= 1200, 3.0 * (np.sin(2 * np.pi * (k - 1200) / 240.0) > 0), 0.0)
    pv = 50.0 + np.convolve(cycle, np.ones(9) / 9, mode="same") + 0.1 * rng.normal(size=k.size)
    found = suspect_onset(pv, None)
    assert found is not None and found.signal == "PV" and abs(found.sample - 1200) <= 150
