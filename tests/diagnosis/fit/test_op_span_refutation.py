"""A declared travel span that OP contradicts is refuted, and the answer never depends on it.

Recordings come from the independent closed-loop simulator (:mod:`valve_emulator.benchmark.independent`, not
the search's model). OP is mapped by positive affine maps as users' exports do it — any scale and offset, a
mean-centred OP, an OP normalised to ±1 — and the standard layout (``t,sp,op,mv,pv``, which declares OP in %
of travel) is checked against the span 0..100: an OP that goes below 0 or above 100 % by clearly more than its
noise, whatever share of its range that is, must be refuted; an OP well inside the span must not be.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import valve_emulator as ve
from valve_emulator.benchmark.independent import draw
from valve_emulator.diagnosis.answers import Reason
from valve_emulator.diagnosis.fit.frame import Frame, jitter_sigma, robust_range
from valve_emulator.recordings.recording import Recording

PERCENT = Frame.travel_percent(source="standard format")
FAMILIES = ("flow_sticky", "healthy_flow", "level_sticky")


@cache
def _loop(family: str, seed: int) -> Recording:
    return draw(family, np.random.default_rng(seed))[0]


def _centred(op: np.ndarray) -> tuple[float, float]:
    return 1.0, -float(np.median(op))


def _plus_minus_one(op: np.ndarray) -> tuple[float, float]:
    lo, hi = robust_range(op)
    return 2.0 / (hi - lo), -(hi + lo) / (hi - lo)


def _affine(a: float, b: float):
    return lambda op: (a, b)


NAMED = {"centred on 0": _centred, "normalised to ±1": _plus_minus_one}
maps = st.one_of(st.sampled_from(list(NAMED.values())),
                 st.builds(_affine, st.floats(-3.0, 3.0).map(lambda e: 10.0 ** e), st.floats(-200.0, 200.0)))
loops = st.builds(_loop, st.sampled_from(FAMILIES), st.integers(0, 3))


def _mapped(rec: Recording, how) -> np.ndarray:
    a, b = how(rec.op)
    return a * rec.op + b


def _clearly_outside(op: np.ndarray) -> bool:
    """Beyond 0..100 by five noise σ (the rule refutes at two), or centred on 0."""
    lo, hi = robust_range(op)
    margin = 5.0 * jitter_sigma(op)
    return lo < -margin or hi > 100.0 + margin or abs(float(np.median(op))) <= margin


def _clearly_inside(op: np.ndarray) -> bool:
    lo, hi = robust_range(op)
    return lo >= 0.0 and hi <= 100.0 and hi - lo >= 1.0


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(rec=loops, how=maps)
def test_an_op_beyond_the_span_by_more_than_its_noise_refutes_it_and_one_inside_does_not(rec, how):
    op = _mapped(rec, how)
    sentence = PERCENT.refutation(op, moving=True)
    if _clearly_outside(op):
        assert sentence and "OP is not in those units" in sentence
    if _clearly_inside(op):
        assert sentence == ""


@pytest.mark.parametrize("name", list(NAMED))
@pytest.mark.parametrize("family", FAMILIES)
def test_a_centred_or_normalised_op_is_never_taken_for_percent_travel(family, name):
    op = _mapped(_loop(family, 0), NAMED[name])
    assert PERCENT.refutation(op, moving=True)
    assert PERCENT.refutation(op, moving=False)


def test_an_op_that_is_noise_around_zero_refutes_the_span():
    op = np.random.default_rng(5).normal(scale=0.3, size=3000)
    assert PERCENT.refutation(op, moving=False)


def test_an_op_clamped_at_the_travel_stops_is_kept_as_percent():
    """A DCS clamps OP in % at its limits: an OP that rests on 0 and 100 % is not beyond them."""
    op = np.clip(50.0 + 70.0 * np.sin(np.arange(3000) / 40.0), 0.0, 100.0)
    assert PERCENT.refutation(op, moving=True) == ""


def _write_standard(path, rec: Recording, op: np.ndarray) -> None:
    rows = (",".join([repr(float(t)), repr(float(s)), repr(float(o)), "", repr(float(p))])
            for t, s, o, p in zip(rec.t, rec.sp, op, rec.pv))
    path.write_text("t,sp,op,mv,pv\n" + "\n".join(rows) + "\n", encoding="utf-8")


@pytest.mark.slow
@settings(max_examples=4, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(rec=st.builds(_loop, st.sampled_from(FAMILIES[:2]), st.integers(0, 3)),
       how=st.one_of(st.sampled_from(list(NAMED.values())),
                     st.builds(_affine, st.floats(0.5, 2.0), st.floats(-150.0, -60.0))))
def test_the_answer_never_depends_on_a_span_the_op_contradicts(tmp_path, rec, how):
    """Read through the standard layout (OP declared in %) and as generic CSV (nothing declared): a contradicted
    span is refuted with its note, and the answer, its reasons and the findings are those of the generic read."""
    op = _mapped(rec, how)
    assert _clearly_outside(op)
    path = tmp_path / "loop.csv"
    _write_standard(path, rec, op)
    standard = ve.diagnose(path)
    generic = ve.diagnose(path, fmt="csv", time="t", op="op", pv="pv", sp="sp")
    codes = [c for c, _ in standard.reasons]
    assert Reason.OP_UNITS_REFUTED in codes
    assert dict(standard.reasons)[Reason.OP_UNITS_REFUTED] in standard.notes
    assert standard.answer is generic.answer, standard.verdict
    assert [c for c in codes if c is not Reason.OP_UNITS_REFUTED] == [c for c, _ in generic.reasons]
    assert [f.physics for f in standard.findings] == [f.physics for f in generic.findings]
