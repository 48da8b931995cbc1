"""Every finding in a diagnosis' JSON carries the 95 % intervals of its parameters, in the units of its values.

A finding's ``intervals`` maps each numeric parameter that has one to ``[lo, hi]``: the interval holds the value,
moves with an affine map of OP exactly as the value does (a band scales, a level on the travel scale maps
affinely), agrees with the ``friction`` estimate, and a parameter on an edge of the range searched is a bound:
its interval is open (null) on the far side.
"""

from __future__ import annotations

import dataclasses
import json

import jsonschema
import numpy as np
import pytest
from historian import STEPS_300, flow_limited_loop, simulate

import valve_emulator as ve
from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis.candidates.characteristic import R_MAX
from valve_emulator.diagnosis.report.schema import schema

#: OP exported in 4–20 mA: op_mA = MA_SCALE · op_% + MA_OFFSET.
MA_SCALE, MA_OFFSET = 0.16, 4.0


def _valid(doc: dict) -> dict:
    """``doc`` as a JSON reader gets it, checked against the schema shipped with the package."""
    doc = json.loads(json.dumps(doc, allow_nan=False))
    jsonschema.validate(doc, schema(), cls=jsonschema.Draft202012Validator)
    return doc


def _finding(doc: dict, physics: str) -> dict:
    return next(f for f in doc["findings"] if f["physics"] == physics)


def _assert_intervals_hold_their_values(doc: dict) -> None:
    for f in doc["findings"]:
        for name, (lo, hi) in f["intervals"].items():
            value = f["parameters"][name]
            assert (lo is None or lo <= value) and (hi is None or value <= hi), (f["physics"], name, value, lo, hi)


@pytest.fixture(scope="module")
def sticky():
    """A sticky loop (S = 4, J = 1 % travel) as plant data, OP in % travel."""
    return simulate([2.0], [12.0, 1.0], 4.0, 0.5, 12.0, S=4.0, J=1.0, duration=900.0, sp_steps=STEPS_300)


@pytest.fixture(scope="module")
def sticky_doc(sticky):
    return _valid(ve.diagnose(sticky).to_json())


def test_a_valve_finding_has_an_interval_for_each_parameter_holding_its_value(sticky_doc):
    stiction = _finding(sticky_doc, "stiction")
    assert set(stiction["intervals"]) == set(stiction["parameters"]) == {"S", "J"}
    _assert_intervals_hold_their_values(sticky_doc)
    lo, hi = stiction["intervals"]["S"]
    assert lo < hi and lo <= 4.0 * 1.1 and hi >= 4.0 * 0.9      # about the truth, S = 4 % travel


def test_a_finding_s_intervals_are_the_friction_estimate_s(sticky_doc):
    stiction, friction = _finding(sticky_doc, "stiction"), sticky_doc["friction"]
    for key in ("S", "J"):
        assert stiction["intervals"][key] == friction[key]["interval"]
        assert stiction["parameters"][key] == friction[key]["value"]


def test_intervals_in_ma_are_those_in_percent_under_the_same_map(sticky, sticky_doc):
    """A band (S, J) scales with OP's scale and ignores its offset, in the finding as in the value."""
    ma = {"t": sticky.t, "op": MA_SCALE * sticky.op + MA_OFFSET, "pv": sticky.pv, "sp": sticky.sp}
    doc = _valid(ve.diagnose(ma).to_json())
    _assert_intervals_hold_their_values(doc)
    pct, got = _finding(sticky_doc, "stiction"), _finding(doc, "stiction")
    for key in ("S", "J"):
        assert got["parameters"][key] == pytest.approx(MA_SCALE * pct["parameters"][key], rel=1e-3)
        assert got["intervals"][key] == pytest.approx([MA_SCALE * x for x in pct["intervals"][key]], rel=1e-3)


@pytest.mark.slow  # two diagnoses of a 3,200-sample record
def test_a_level_s_interval_maps_affinely_with_op():
    """A flow limit at 70 % travel, found from OP in % and from OP in mA (each with its span declared): the
    limit's interval in mA is the one in % under op_mA = 0.16 op_% + 4, offset included."""
    sp, op, pv = flow_limited_loop(70.0, 90.0, (40, 60, 35, 85, 45, 30, 55, 40))
    t = np.arange(op.size, dtype=float)
    pct = _valid(ve.diagnose({"t": t, "op": op, "pv": pv, "sp": sp}, op_range=(0.0, 100.0)).to_json())
    ma = _valid(ve.diagnose({"t": t, "op": MA_SCALE * op + MA_OFFSET, "pv": pv, "sp": sp},
                            op_range=(MA_OFFSET, MA_OFFSET + 100.0 * MA_SCALE)).to_json())
    for doc in (pct, ma):
        _assert_intervals_hold_their_values(doc)
    lo, hi = _finding(pct, "saturation")["intervals"]["hi"]
    assert lo < 70.0 + 2.0 and hi > 70.0 - 2.0
    assert _finding(ma, "saturation")["intervals"]["hi"] == pytest.approx(
        [MA_SCALE * lo + MA_OFFSET, MA_SCALE * hi + MA_OFFSET], rel=1e-3)


@pytest.mark.slow  # a whole diagnosis with a model (about 20 s)
def test_a_parameter_on_an_edge_of_the_range_searched_has_an_interval_open_on_its_far_side():
    """A curve steeper than any searched: R sits on the top edge, a bound (R ≥ R_MAX), so its interval starts
    there and has no upper end."""
    case = next(c for c in CASES if c.name == "equal-percentage characteristic")
    case = dataclasses.replace(case, loop={**case.loop, "valve": {**case.loop["valve"], "rangeability": 3000.0}})
    rec, nominal, _ = generate(case, duration=2600.0)
    doc = _valid(ve.diagnose(rec, nominal).to_json())
    found = _finding(doc, "characteristic")
    assert found["parameters"]["R"] == pytest.approx(R_MAX)
    assert found["intervals"] == {"R": [pytest.approx(R_MAX), None]}     # the type, a word, has none
    _assert_intervals_hold_their_values(doc)
