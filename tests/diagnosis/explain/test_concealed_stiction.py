"""Stiction concealed in closed-loop OP/PV with PV noise is found, fitted and explains the data.

Every recording here is a closed loop simulated with a sticky valve; the diagnosis sees only ``t, op, pv``
(no valve position, no set point), PV measurement noise of 5 % of the PV amplitude inside the loop, and a
record that starts mid-cycle. The nominal model has the right plant and a linear valve.
"""

from __future__ import annotations

import pytest

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.diagnosis import diagnose

pytestmark = pytest.mark.slow  # each test fits a whole concealed recording (seconds)

SECONDS = 3300.0  # 3000 samples after the cut: ~20 limit cycles of the concentration loop
BY_NAME = {c.name: c for c in CASES}
STICTION = ["stiction, undershoot", "stiction, no offset", "stiction, overshoot"]


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("name", STICTION)
def test_concealed_stiction_is_named_fitted_and_explains_the_recording(name, seed):
    case = BY_NAME[name]
    assert case.noise == 0.05
    rec, nominal, _ = generate(case, duration=SECONDS, seed=seed)
    assert rec.has_mv is False and rec.has_sp is False
    d = diagnose(rec, nominal)
    truth = case.truth["stiction"]
    assert [f.physics for f in d.findings] == ["stiction"], d.verdict
    found = d.findings[0].parameters
    assert abs(found["S"] - truth["S"]) <= 0.5, found
    assert abs(found["J"] - truth["J"]) <= 1.0, found
    assert d.fit_after >= 90.0
    assert d.fit_after - d.fit_before >= 20.0
    assert d.verdict.startswith("the model leaves out valve stiction: S ≈")


def test_stiction_in_an_integrating_loop_is_named_and_fitted():
    case = BY_NAME["stiction, level loop"]
    rec, nominal, _ = generate(case, duration=800.0)
    d = diagnose(rec, nominal)
    assert [f.physics for f in d.findings] == ["stiction"], d.verdict
    found = d.findings[0].parameters
    assert abs(found["S"] - 3.0) <= 0.5 and abs(found["J"] - 1.5) <= 1.0
    assert d.fit_after - d.fit_before >= 20.0


def test_a_dead_time_two_samples_off_does_not_bias_the_slip_jump():
    # Same loop and valve; the true dead time is 12 s = nominal + 2 samples. Searching θ with S and J
    # keeps J where it is with the right dead time (a wrong θ would pass for less slip jump).
    off = BY_NAME["stiction + dead time off by 2 samples"]
    rec, nominal, true_cfg = generate(off, duration=SECONDS)
    assert true_cfg.plant.delay - nominal.plant.delay == pytest.approx(2 * rec.dt)
    d_off = diagnose(rec, nominal)
    d_ok = diagnose(rec, _without_valve(true_cfg))  # the nominal with the right dead time
    found = {f.physics: f.parameters for f in d_off.findings}
    assert set(found) == {"stiction", "dead_time"}, d_off.verdict
    assert found["dead_time"]["theta"] == pytest.approx(12.0, abs=0.5)
    J_off = found["stiction"]["J"]
    J_ok = d_ok.findings[0].parameters["J"]
    assert abs(J_off - 2.0) <= 1.0 and abs(J_off - J_ok) <= 1.0
    assert abs(found["stiction"]["S"] - 5.0) <= 0.5


def _without_valve(cfg):
    import dataclasses

    return dataclasses.replace(cfg, valve=dataclasses.replace(cfg.valve, S=0.0, J=0.0, seed_form=None),
                               plant=dataclasses.replace(cfg.plant, noise=0.0))
