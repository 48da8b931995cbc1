"""Every other effect of the proof table is named correctly; the control gets no finding.

Closed loops with one piece of physics left out of the nominal model, concealed as in ``prove`` (only
``t, op, pv``, PV noise inside the loop, the record starting mid-run), at about 60 % of the proof's lengths.
"""

from __future__ import annotations

import pytest

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis import diagnose

pytestmark = pytest.mark.slow  # each test fits a whole concealed recording (seconds)

BY_NAME = {c.name: c for c in CASES}


def _run(name: str, duration: float):
    case = BY_NAME[name]
    rec, nominal, _ = generate(case, duration=duration)
    d = diagnose(rec, nominal)
    return case, d, {f.physics: f.parameters for f in d.findings}


def test_pure_deadband_is_named_deadband_not_stiction():
    _, d, found = _run("pure deadband, level loop", 800.0)
    assert list(found) == ["deadband"], d.verdict
    assert found["deadband"]["S"] == pytest.approx(3.0, abs=0.5)
    assert d.fit_after >= 90.0


def test_dead_time_error_is_named_and_estimated():
    _, d, found = _run("dead-time error", 2600.0)
    assert list(found) == ["dead_time"], d.verdict
    assert found["dead_time"]["theta"] == pytest.approx(8.0, abs=0.5)  # nominal 5 s
    assert "(nominal 5 s)" in d.verdict


def test_equal_percentage_characteristic_is_named_with_its_rangeability():
    _, d, found = _run("equal-percentage characteristic", 2600.0)
    assert list(found) == ["characteristic"], d.verdict
    assert found["characteristic"]["type"] == "equal_percentage"
    assert 20.0 <= found["characteristic"]["R"] <= 45.0  # truth 30
    assert d.fit_after - d.fit_before >= 20.0


def test_actuator_lag_is_named_and_estimated():
    _, d, found = _run("actuator lag", 2600.0)
    assert list(found) == ["actuator_lag"], d.verdict
    assert found["actuator_lag"]["tau"] == pytest.approx(4.0, abs=1.0)


@pytest.mark.parametrize("seed", [1, 2])
def test_control_case_gets_no_finding(seed):
    case = BY_NAME["control (nothing left out)"]
    rec, nominal, _ = generate(case, duration=2600.0, seed=seed)
    d = diagnose(rec, nominal)
    assert d.findings == (), d.verdict
    assert d.to_json()["findings"] == []
    assert d.verdict.startswith("no significant mismatch")
    assert d.fit_after == pytest.approx(d.fit_before, abs=1.0)
