"""OP and PV in any units: a positive affine map of OP (scale 10⁻³…10³, any offset, mean-centring, 4–20 mA,
raw counts) and of PV changes neither the answer nor the findings, and S and J move with the map.

Concealed closed loops of the project's simulator (only t, sp, op, pv kept): stiction with undershoot and
with overshoot, a deadband, a linear loop under an oscillating load, a linear loop tuned aggressively.
Records are short (600 samples) and examples few, to keep the file fast.
"""

from __future__ import annotations

from dataclasses import replace
from functools import cache

import pytest
from historian import STEPS_300, simulate
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from valve_emulator.diagnosis.answers import Answer
from valve_emulator.diagnosis.assess.decision import assess_uniform
from valve_emulator.diagnosis.fit.frame import Frame

pytestmark = pytest.mark.slow

PLANT = ([2.0], [12.0, 1.0], 4.0)
CASES = {
    "stiction, undershoot": dict(kc=0.5, ti=12.0, S=4.0, J=1.0),
    "stiction, overshoot": dict(kc=0.5, ti=12.0, S=3.0, J=5.0),
    "deadband": dict(kc=0.5, ti=12.0, S=4.0, J=0.0, sp_steps=STEPS_300),
    "oscillating load": dict(kc=0.5, ti=12.0, sp_steps=STEPS_300, noise=0.1,
                             disturbance={"type": "sine", "amplitude": 3.0, "period": 180.0}),
    "aggressive tuning": dict(kc=2.2, ti=6.0),
}


@cache
def _record(name: str):
    kw = dict(CASES[name])
    kc, ti = kw.pop("kc"), kw.pop("ti")
    return simulate(*PLANT, kc, ti, duration=800.0, **{"noise": 0.05, **kw})


@cache
def _base(name: str):
    return assess_uniform(_record(name))


def _mapped(name: str, a: float, b: float, c: float, d: float):
    rec = _record(name)
    return replace(rec, op=a * rec.op + b, pv=c * rec.pv + d, sp=None if rec.sp is None else c * rec.sp + d)


def _findings(a):
    return () if a.diagnosis is None else a.diagnosis.findings


def _assert_same(name: str, a: float, b: float, c: float = 1.0, d: float = 0.0):
    """Assert that the mapped record gives the base record's answer, reasons and findings, and S, J that follow
    the map; return the mapped record's assessment."""
    base, got = _base(name), assess_uniform(_mapped(name, a, b, c, d))
    assert got.decision == base.decision, (got.verdict, base.verdict)
    assert [r for r, _ in got.reasons] == [r for r, _ in base.reasons]
    assert [f.physics for f in _findings(got)] == [f.physics for f in _findings(base)]
    if base.decision is Answer.STICTION:
        assert pytest.approx(a * base.S, rel=0.05) == got.S
        assert pytest.approx(a * base.J, rel=0.05, abs=0.05 * a * base.S) == got.J
        lo, hi = got.intervals["S"]
        assert lo == pytest.approx(a * base.intervals["S"][0], rel=0.05)
    return got


scales = st.floats(min_value=-3.0, max_value=3.0).map(lambda e: 10.0 ** e)


@pytest.mark.parametrize("name", list(CASES))
@settings(max_examples=2, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(a=scales, b=st.floats(min_value=-1e3, max_value=1e3), c=scales, d=st.floats(min_value=-1e3, max_value=1e3))
def test_random_positive_affine_maps_of_op_and_pv_change_nothing(name, a, b, c, d):
    _assert_same(name, a, b * a, c, d * c)


@pytest.mark.parametrize("how", ["deviation from 50 %", "mean-centred, unit variance", "0-1 fraction",
                                 "4-20 mA", "raw counts 0-27648"])
def test_the_exports_a_user_meets_give_the_stiction_answer_and_s_j_in_op_units(how):
    op = _record("stiction, undershoot").op
    a, b = {"deviation from 50 %": (1.0, -50.0), "mean-centred, unit variance": (1 / op.std(), -op.mean() / op.std()),
            "0-1 fraction": (0.01, 0.0), "4-20 mA": (0.16, 4.0), "raw counts 0-27648": (276.48, 0.0)}[how]
    assert _assert_same("stiction, undershoot", a, b).decision is Answer.STICTION


def test_a_known_span_gives_s_and_j_in_percent_of_travel_too():
    rec = _mapped("stiction, undershoot", 0.16, 4.0, 1.0, 0.0)          # OP in mA
    ma = assess_uniform(rec, frame=Frame.travel_percent((4.0, 20.0), source="op_range"))
    pct = assess_uniform(_record("stiction, undershoot"), frame=Frame.travel_percent())
    assert ma.decision is pct.decision is Answer.STICTION
    assert pytest.approx(0.16 * pct.S, rel=0.02) == ma.S
    assert ma.frame.travel(ma.S) == pytest.approx(pct.S, rel=0.02)
    assert 3.0 < pct.S < 5.0                                              # the truth: S = 4 % travel
