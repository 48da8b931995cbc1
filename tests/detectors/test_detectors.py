"""Comparison stiction detectors (valve_emulator.detectors): known-truth numerics and simulated loops.

The loops are the 2003 paper's concentration loop (plant 3 e^(-10 s)/(10 s + 1), PI kc 0.2, ti 10 s) run by the
project's own simulator at dt = 1 s and kept every 5 s, as a plant historian would store them.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import signal

from valve_emulator.config import loop_from_mapping
from valve_emulator.detectors import (
    DECISIONS,
    DETECTORS,
    DetectorResult,
    bicoherence,
    he_curve_fit,
    horch,
    oscillation,
    run_detectors,
)
from valve_emulator.detectors.bicoherence import gaussianity_indices, squared_bicoherence
from valve_emulator.detectors.ellipse import fit_ellipse, width_along_x
from valve_emulator.simulation.loop import simulate_loop

HISTORIAN = 5        # keep every 5th sample of the 1 s simulation
BURN_IN = 500        # s, the start-up transient


def loop(*, S=5.0, J=2.0, disturbance=None, noise=0.05, seed=1, duration=4000.0, level=False):
    plant = ({"integrator": {"gain": 1.0}} if level else {"num": [3.0], "den": [10.0, 1.0], "delay": 10.0})
    plant["noise"] = noise
    if disturbance is not None:
        plant["disturbance"] = disturbance
    cfg = loop_from_mapping({
        "valve": {"model": "kano", "S": S, "J": J},
        "plant": plant,
        "controller": {"kc": 0.4, "ti": 2.0} if level else {"kc": 0.2, "ti": 10.0},
        "simulation": {"dt": 1.0, "duration": duration, "seed": seed},
    })
    cfg = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, sp_steps=((10.0, 1.0),)))
    rec = simulate_loop(cfg)
    step = 1 if level else HISTORIAN
    keep = slice(BURN_IN, None, step)
    return rec.op[keep], rec.pv[keep], rec.sp[keep], rec.dt * step


@pytest.fixture(scope="module")
def sticky():
    return loop()                                         # S = 5, J = 2: the brief's sticky loop


@pytest.fixture(scope="module")
def disturbed():
    return loop(S=0.0, J=0.0, disturbance={"type": "sine", "amplitude": 5.0, "period": 100.0})


@pytest.fixture(scope="module")
def noisy():
    return loop(S=0.0, J=0.0, noise=0.1)


def run(data, **kw):
    op, pv, sp, dt = data
    return run_detectors(op, pv, dt=dt, sp=sp, **kw)


# ------------------------------------------------------------------------------------------- known truth

def test_regularity_finds_a_sine_and_not_white_noise():
    rng = np.random.default_rng(0)
    k = np.arange(1500)
    osc = oscillation(np.sin(2 * np.pi * k / 50.0) + 0.3 * rng.standard_normal(k.size))
    assert osc.regular and osc.period == pytest.approx(50.0, rel=0.02)
    assert not oscillation(rng.standard_normal(k.size)).regular


@pytest.mark.parametrize("phase_deg, delta, decision", [
    (0, 0.0, "no stiction"), (20, 0.222, "no stiction"), (45, 0.5, "undetermined"),
    (90, 1.0, "stiction"), (180, 0.0, "no stiction"),
])
def test_horch_delta_is_the_phase_over_90_degrees(phase_deg, delta, decision):
    k = np.arange(2000)
    u = np.sin(2 * np.pi * k / 50.0)
    y = np.sin(2 * np.pi * k / 50.0 - np.radians(phase_deg))
    res = horch(u, y, dt=2.0)
    assert res.indices["delta"] == pytest.approx(delta, abs=0.01)
    assert res.decision == decision
    assert res.indices["period_s"] == pytest.approx(100.0, rel=0.01)


def test_he_index_separates_a_triangle_from_a_sine():
    rng = np.random.default_rng(1)
    k = np.arange(1200)
    tri = signal.sawtooth(2 * np.pi * k / 60.0, width=0.5) + 0.02 * rng.standard_normal(k.size)
    sine = np.sin(2 * np.pi * k / 60.0) + 0.02 * rng.standard_normal(k.size)
    flat = np.zeros(k.size)
    r_tri = he_curve_fit(tri, flat, dt=1.0)
    r_sin = he_curve_fit(sine, flat, dt=1.0)
    assert r_tri.decision == "stiction" and r_tri.indices["si"] > 0.8
    assert r_sin.decision == "no stiction" and r_sin.indices["si"] < 0.1
    # integrating=True fits the PV instead of the OP
    assert he_curve_fit(flat + 1.0, tri, dt=1.0, integrating=True).decision == "stiction"


def test_bicoherence_finds_quadratic_phase_coupling_and_not_gaussian_noise():
    rng = np.random.default_rng(2)
    n = 4096
    t = np.arange(n)
    ph1, ph2 = (np.cumsum(0.05 * rng.standard_normal(n)) for _ in range(2))   # slowly wandering phases
    f1, f2 = 10 / 64, 6 / 64
    coupled = (np.cos(2 * np.pi * f1 * t + ph1) + np.cos(2 * np.pi * f2 * t + ph2)
               + np.cos(2 * np.pi * (f1 + f2) * t + ph1 + ph2) + 0.5 * rng.standard_normal(n))
    bic2, k = squared_bicoherence(coupled)
    assert bic2.max() > 0.8
    ngi, nli = gaussianity_indices(bic2, k)
    assert ngi > 0.001 and nli > 0.01
    y = signal.lfilter(*signal.butter(2, 0.15), rng.standard_normal(n))
    bic2, k = squared_bicoherence(y / y.std())
    assert np.mean(bic2) == pytest.approx(1.0 / k, rel=0.25)     # the Gaussian level, 1/K
    assert gaussianity_indices(bic2, k)[0] <= 0.001
    bic2, k = squared_bicoherence(y + 0.5 * y**2)                   # a static quadratic nonlinearity
    assert gaussianity_indices(bic2, k)[0] > 0.001


def test_ellipse_width_along_op_is_the_published_chord():
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    rng = np.random.default_rng(3)
    for phi in (0.3, 1.0, 1.5):
        op = 50 + 3 * np.cos(t) + 0.01 * rng.standard_normal(t.size)
        pv = 970 + 20 * np.cos(t - phi)
        assert width_along_x(fit_ellipse(op, pv)) == pytest.approx(6 * np.sin(phi), rel=0.02)
    assert fit_ellipse(np.arange(10.0), 2 * np.arange(10.0)) is None     # a line is not an ellipse


# --------------------------------------------------------------------------------------- simulated loops

def test_sticky_limit_cycle_is_detected_by_horch_and_he(sticky):
    res = run(sticky)
    assert res["horch"].decision == "stiction", res["horch"].report()
    assert res["he"].decision == "stiction", res["he"].report()
    assert res["he"].indices["period_s"] == pytest.approx(140.0, rel=0.1)


def test_bicoherence_detects_an_overshooting_sticky_valve():
    # On the S=5, J=2 loop the bicoherence test is erratic (NGI near its threshold, seed-dependent; see the
    # report); with overshoot (J > S) the limit cycle is asymmetric enough to be found every time.
    op, pv, sp, dt = loop(J=7.0)
    res = bicoherence(op, pv, dt=dt, sp=sp)
    assert res.decision == "stiction", res.report()
    assert res.indices["ngi"] > 0.001 and res.indices["nli"] > 0.01
    assert 3.0 < res.indices["apparent_stiction"] < 7.0                  # % of OP, S = 5


def test_linear_loop_with_sinusoidal_disturbance_is_not_called_stiction(disturbed):
    for _name, res in run(disturbed).items():
        assert res.decision != "stiction", res.report()
    assert run(disturbed)["he"].decision == "no stiction"


def test_noise_only_is_not_called_stiction(noisy):
    for _name, res in run(noisy).items():
        assert res.decision in ("no stiction", "undetermined"), res.report()


def test_integrating_loop_he_fits_pv_and_horch_does_not_apply():
    op, pv, sp, dt = loop(S=3.0, J=1.5, level=True, noise=0.02)
    res = run_detectors(op, pv, dt=dt, sp=sp, integrating=True)
    assert res["horch"].decision == "not applicable"
    assert res["he"].decision == "stiction", res["he"].report()


# ------------------------------------------------------------------------------------ interface and input

def test_registry_and_results():
    assert list(DETECTORS) == ["horch", "he", "bicoherence"]
    k = np.arange(300.0)
    res = run_detectors(np.sin(k / 5), np.cos(k / 5), dt=1.0, names=["he"])
    assert list(res) == ["he"] and res["he"].decision in DECISIONS
    assert res["he"].report().startswith("he: ")
    with pytest.raises(ValueError, match="unknown detector"):
        run_detectors(k, k, dt=1.0, names=["area"])
    with pytest.raises(ValueError, match="decision must be one of"):
        DetectorResult("x", "maybe")
    frozen = DetectorResult("x", "stiction", {"a": 1})
    with pytest.raises(dataclasses.FrozenInstanceError):
        frozen.decision = "no stiction"
    with pytest.raises(TypeError):
        frozen.indices["a"] = 2.0


@pytest.mark.parametrize("name", list(DETECTORS))
def test_bad_input_raises_and_poor_data_is_undetermined(name):
    detector = DETECTORS[name]
    x = np.sin(np.arange(400) / 5.0)
    bad = x.copy()
    bad[7] = np.nan
    with pytest.raises(ValueError, match=r"op must be finite, got nan at index 7"):
        detector(bad, x, dt=1.0)
    with pytest.raises(ValueError, match="same length"):
        detector(x, x[:-1], dt=1.0)
    with pytest.raises(ValueError, match="dt must be"):
        detector(x, x, dt=0.0)
    assert detector(x[:20], x[:20], dt=1.0).decision == "undetermined"          # too short
    assert detector(np.full(400, 50.0), np.full(400, 1.0), dt=1.0).decision == "undetermined"   # flat
    # a set point with gaps (NaN = not recorded) is ignored, not an error
    sp = np.full(400, np.nan)
    assert detector(x, np.roll(x, 3), dt=1.0, sp=sp).decision in DECISIONS
