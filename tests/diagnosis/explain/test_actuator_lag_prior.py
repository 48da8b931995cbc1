"""A nominal model is a prior: an actuator lag the model leaves out is attributed to the actuator, not traded
against the plant's time constant the model has right (τ = 10 s); without a model the two cannot be told apart,
and the finding says so."""

from __future__ import annotations

import numpy as np
import pytest

import valve_emulator as ve
from valve_emulator.benchmark.cases import Case, generate, loop_mapping, setpoint_steps
from valve_emulator.diagnosis.candidates import get


def _case(lag: float) -> Case:
    return Case(f"actuator lag {lag:g} s", {"actuator_lag": {"tau": lag}},
                loop_mapping([1.0], [10.0, 1.0], 2.0, 1.2, 10.0, duration=2300.0,
                             sp_steps=setpoint_steps([3, -3, 5, 0, -4, 2, 4, -1] * 2, 170.0)),
                {}, noise=0.03, lag=lag)


@pytest.mark.slow
@pytest.mark.parametrize("lag", [6.0, 15.0])
def test_with_the_nominal_model_the_actuator_lag_is_found_within_two_seconds(lag):
    rec, nominal, _ = generate(_case(lag))
    d = ve.diagnose(rec, nominal)
    found = {f.physics: f.parameters for f in d.findings}
    assert set(found) == {"actuator_lag"}, d.verdict
    assert abs(found["actuator_lag"]["tau"] - lag) <= 2.0
    refitted = float(d.explanation.linear["time constants (s)"][1])
    assert abs(refitted - 10.0) <= 2.0          # the plant keeps the model's time constant


def test_without_a_model_an_actuator_lag_is_reported_as_inseparable_from_a_plant_lag():
    lag = get("actuator_lag")
    assert "cannot separate" in lag.describe(np.array([6.0]), None)
    assert "cannot" not in lag.describe(np.array([6.0]), {"theta": 2.0})
