"""The answer on two records that real plants produce: a finely quantised PV over a stiction cycle, and a PV
that stays flat while OP travels far (the answer "no response"), or while OP only dithers ("cannot tell")."""

from __future__ import annotations

import numpy as np
from historian import simulate

from valve_emulator.diagnosis.answers import Answer, Reason
from valve_emulator.diagnosis.assess.decision import assess
from valve_emulator.recordings.recording import Recording

RNG = np.random.default_rng(6)


def test_a_pv_quantised_at_one_percent_of_its_cycle_over_a_stiction_cycle_is_still_stiction():
    rec = simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, S=4.0, J=1.0, duration=1100.0, noise=0.02)
    amplitude = 0.5 * (np.percentile(rec.pv, 99) - np.percentile(rec.pv, 1))
    q = 0.01 * amplitude
    stepped = Recording(rec.t, rec.sp, rec.op, None, q * np.round(rec.pv / q), source="quantised")
    assert np.allclose(stepped.pv / q, np.round(stepped.pv / q)) and np.unique(stepped.pv).size < 300
    a = assess(stepped)
    assert a.decision is Answer.STICTION, a.verdict
    codes = [c for c, _ in a.reasons]
    assert codes[0] in (Reason.STICTION, Reason.DEADBAND)
    assert set(codes) <= {Reason.STICTION, Reason.DEADBAND, Reason.QUANTIZATION, Reason.WEAK_EVIDENCE}
    assert 3.0 < a.S < 5.0


def _flat_pv_record(op: np.ndarray) -> Recording:
    t = np.arange(float(op.size))
    pv = np.full(op.size, 12.5) + np.r_[0.01 * RNG.normal(size=40), np.zeros(op.size - 40)]
    return Recording(t, None, op, None, pv, source="flat")


def test_a_flat_pv_while_op_travels_twenty_percent_is_the_answer_no_response():
    op = 40.0 + 20.0 * (np.arange(800) // 100 % 2) + 0.2 * RNG.normal(size=800)   # OP travels 20 % and back
    a = assess(_flat_pv_record(op))
    assert a.decision is Answer.NO_RESPONSE and a.decision.needs_attention and a.explanation is None
    assert [c for c, _ in a.reasons] == [Reason.NO_RESPONSE]
    assert "inspect it" in a.reason and a.statement.startswith("no response: PV is flat")
    assert "seized valve" in a.reason and "closed block valve" in a.reason and "dead transmitter" in a.reason


def test_a_flat_pv_while_op_only_dithers_is_a_flat_pv_not_a_missing_response():
    op = 40.0 + 0.2 * RNG.normal(size=800)
    a = assess(_flat_pv_record(op))
    assert a.decision is Answer.CANNOT_TELL and [c for c, _ in a.reasons] == [Reason.FLAT_PV]
    assert not a.decision.needs_attention
