"""A record one linear model does not explain is assessed again as two halves (assess/decision.py, step 4).

Known truth: the proof cases' concentration loop — with concealed stiction (S = 5, J = 2 % travel), or with
nothing left out — for 1,300 s, followed by as long a stretch in which PV is a random walk of its own that OP
does not drive (a transmitter gone bad, a loop put on another duty). No single linear model explains the
whole; the first half is the loop itself.
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis.answers import Answer, Reason
from valve_emulator.diagnosis.assess.decision import assess
from valve_emulator.recordings.recording import Recording

pytestmark = pytest.mark.slow


@functools.cache
def _with_a_bad_second_half(case_index: int, seed: int) -> tuple[Recording, int]:
    case = CASES[case_index]
    loop, _, _ = generate(case, duration=1300 + case.cut)
    n = len(loop)
    walk = np.cumsum(np.random.default_rng(seed).normal(0.0, 1.0, n)) * np.std(loop.pv) / 3
    rec = Recording(np.arange(2 * n) * loop.dt, None, np.concatenate([loop.op, loop.op[::-1]]), None,
                    np.concatenate([loop.pv, loop.pv[-1] + walk]), source=f"{case.name} + bad half")
    return rec, n


def _codes(a) -> list[Reason]:
    return [code for code, _ in a.reasons]


@functools.cache
def _sticky_assessed():
    return assess(_with_a_bad_second_half(0, seed=3)[0])


def test_stiction_is_found_on_the_half_that_a_model_explains():
    _, n = _with_a_bad_second_half(0, seed=3)
    a = _sticky_assessed()
    assert a.decision is Answer.STICTION, a.reason
    assert Reason.PART_OF_RECORD in _codes(a)
    assert f"those of samples 0–{n - 1}" in a.reason
    assert any(note == f"answered on samples 0–{n - 1} of {2 * n}" for note in a.notes), a.notes
    # The figures are the half's: the concealed valve, in the unit-free frame mapped back to OP (% travel here).
    assert abs(a.S - 5.0) <= 0.5 and abs(a.J - 2.0) <= 0.6, (a.S, a.J)


def test_a_linear_loop_is_answered_no_stiction_on_the_half_that_a_model_explains():
    rec, _ = _with_a_bad_second_half(9, seed=3)
    a = assess(rec)
    assert a.decision is Answer.NO_STICTION, a.reason
    assert Reason.PART_OF_RECORD in _codes(a)


def test_halves_that_disagree_leave_the_record_cannot_tell():
    # Here the random-walk half happens to be "explained" (as no stiction) while the sticky half is stiction:
    # one record, two answers — the record does not decide.
    rec, _ = _with_a_bad_second_half(0, seed=2)
    a = assess(rec)
    assert a.decision is Answer.CANNOT_TELL
    assert _codes(a)[0] is Reason.NOT_EXPLAINED and "halves disagree" in a.reason, a.reason


# Hypothesis' simplest example, the first of three, is the identity map (a, b, c, d) = (1, 0, 1, 0): the record
# itself, whose assessment ``_sticky_assessed`` already holds, so it judged nothing about units. It is rejected and
# one example fewer asked for: two maps other than the identity, as before.
@settings(max_examples=2, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(a=st.floats(-3.0, 3.0).map(lambda e: 10.0 ** e), b=st.floats(-1e3, 1e3),
       c=st.floats(-3.0, 3.0).map(lambda e: 10.0 ** e), d=st.floats(-1e3, 1e3))
def test_answering_by_halves_does_not_depend_on_op_or_pv_units(a, b, c, d):
    assume((a, b, c, d) != (1.0, 0.0, 1.0, 0.0))
    rec, _ = _with_a_bad_second_half(0, seed=3)
    base = _sticky_assessed()
    got = assess(replace(rec, op=a * rec.op + b, pv=c * rec.pv + d))
    assert got.decision is base.decision is Answer.STICTION, got.reason
    assert _codes(got) == _codes(base)
    assert abs(got.S - a * base.S) <= 0.05 * a * base.S and abs(got.J - a * base.J) <= 0.05 * a * base.S


def test_the_document_of_a_record_answered_by_halves_is_valid_and_keeps_the_half_s_model():
    import json

    import jsonschema

    import valve_emulator as ve
    from valve_emulator.diagnosis.report.schema import schema

    rec, n = _with_a_bad_second_half(0, seed=3)
    result = ve.diagnose(rec)
    doc = json.loads(json.dumps(result.to_json()))
    jsonschema.validate(doc, schema(), cls=jsonschema.Draft202012Validator)
    assert doc["answer"] == "stiction" and doc["friction"] is not None
    assert "part_of_record" in [r["code"] for r in doc["reasons"]]
    # The kept model is the loop's: replaying the loop half's OP reproduces its PV (held-out fit well above 0).
    pv = result.predict(rec.op[:n])
    err = np.mean((pv[200:] - rec.pv[200:n]) ** 2) / np.var(rec.pv[200:n])
    assert err < 0.3, err


def test_a_half_whose_pv_stops_responding_answers_no_response_for_the_record():
    # The first half: PV a random walk that OP does not drive (no model explains it); the second: PV frozen
    # for 360 of its 400 samples while OP keeps swinging 20 units — a valve that seized (or a transmitter that
    # froze) halfway. PV is flat over 45 % of the whole, so only the half answers no response.
    rng = np.random.default_rng(1)
    n = 400
    op = 50 + 10 * np.sin(np.arange(2 * n) * 2 * np.pi / 150) + 0.3 * rng.normal(size=2 * n)
    walk = 40 + np.cumsum(rng.normal(0.0, 0.5, n + 40))
    pv = np.concatenate([walk, np.full(n - 40, walk[-1])])
    a = assess(Recording(np.arange(2.0 * n), None, op, None, pv, source="seizes halfway"))
    assert a.decision is Answer.NO_RESPONSE, a.reason
    assert _codes(a) == [Reason.NO_RESPONSE, Reason.PART_OF_RECORD]
    assert a.notes == (f"answered on samples {n}–{2 * n - 1} of {2 * n}",) and a.explanation is None
