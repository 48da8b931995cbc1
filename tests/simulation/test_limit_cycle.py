"""Limit cycles: measurement on known waves, prediction against brute force and against simulation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from valve_emulator.physics.describing_function import describing_function
from valve_emulator.physics.stiction import StictionBank
from valve_emulator.simulation.limit_cycle import (
    loop_frequency_response,
    measure_limit_cycle,
    predict_limit_cycle,
)

LEVEL_PI = (0.4, 2.0, 0.0, "reverse")          # seed Table 1, level loop: Kc 0.4, Ti 2 s
LEVEL_PLANT = ((1.0,), (1.0, 0.0), 0.0)        # G = 1/s
CONC_PI = (0.2, 10.0, 0.0, "reverse")          # concentration loop: Kc 0.2, Ti 10 s
CONC_PLANT = ((3.0,), (10.0, 1.0), 10.0)       # G = 3 e^{-10 s} / (10 s + 1)


# ------------------------------------------------------------------------------------------ measurement

def triangle(t: np.ndarray, period: float, amplitude: float) -> np.ndarray:
    phase = (t / period) % 1.0
    return amplitude * (4 * np.abs(phase - 0.5) - 1)


@pytest.mark.parametrize("wave", ["sine", "triangle"])
def test_measures_known_waves_exactly(wave):
    t = np.arange(0, 200, 0.01)
    period, amplitude = 7.3, 2.5
    wave_0 = np.sin(2 * np.pi * t / period) if wave == "sine" else triangle(t, period, 1.0)
    x = 40 + amplitude * wave_0
    lc = measure_limit_cycle(t, x)
    assert lc.amplitude == pytest.approx(amplitude, rel=1e-2)
    assert lc.period == pytest.approx(period, rel=1e-2)
    assert lc.sustained
    assert lc.n_cycles in (12, 13)  # 100 s of window hold 13.7 periods
    assert lc.level == pytest.approx(40, abs=0.2)


def test_noise_does_not_add_cycles():
    rng = np.random.default_rng(0)
    t = np.arange(0, 200, 0.01)
    clean = np.sin(2 * np.pi * t / 10 + 1.0)  # no crossing right at the window edge
    lc_clean = measure_limit_cycle(t, clean)
    lc = measure_limit_cycle(t, clean + 0.03 * rng.standard_normal(t.size))
    assert lc.n_cycles == lc_clean.n_cycles == 9
    assert lc.period == pytest.approx(10, rel=1e-2)
    assert lc.sustained


def test_decaying_oscillation_is_not_sustained():
    t = np.arange(0, 300, 0.01)
    x = 5 + np.exp(-t / 60) * np.sin(2 * np.pi * t / 8)
    lc = measure_limit_cycle(t, x)
    assert lc.n_cycles >= 2 and not lc.sustained
    assert lc.period == pytest.approx(8, rel=1e-2)


def test_constant_and_invisible_wiggle_are_not_sustained():
    t = np.arange(0, 100, 0.1)
    lc = measure_limit_cycle(t, np.full(t.size, 3.0))
    assert (lc.amplitude, lc.n_cycles, lc.sustained) == (0.0, 0, False) and math.isnan(lc.period)
    # 1e-5 of oscillation on a level of 1000 is below the relative tolerance (1e-3 of the level).
    lc = measure_limit_cycle(t, 1000 + 1e-5 * np.sin(t))
    assert lc.n_cycles > 2 and not lc.sustained


def test_window_leaves_out_the_start_up_transient():
    t = np.arange(0, 400, 0.05)
    x = np.where(t < 150, 10 * np.sin(2 * np.pi * t / 40), np.sin(2 * np.pi * t / 12))
    lc = measure_limit_cycle(t, x, last_fraction=0.5)
    assert lc.period == pytest.approx(12, rel=1e-2) and lc.amplitude == pytest.approx(1, rel=1e-2)


@pytest.mark.parametrize(("t", "x", "kw"), [
    ([0, 1, 2], [0, 1], {}),
    ([0, 1, 1], [0, 1, 2], {}),
    ([0, 1, 2], [0, np.nan, 2], {}),
    ([0, 1, 2], [0, 1, 2], {"last_fraction": 0.0}),
])
def test_measure_rejects_bad_input(t, x, kw):
    with pytest.raises(ValueError):
        measure_limit_cycle(np.asarray(t, float), np.asarray(x, float), **kw)


# ------------------------------------------------------------------------------ prediction: brute force

@pytest.mark.parametrize("J", [0.0, 1.5, 3.0, 4.5])
def test_level_loop_matches_analytic_harmonic_balance(J):
    """G = 1/s with PI: L(jw) = -kc/(ti w^2) - j kc/w, so L = z = -1/N(A) gives w = -kc/Im z and
    Re z + (Im z)^2/(kc ti) = 0, a scalar equation in A solved here on a dense grid."""
    S, kc, ti = 3.0, 0.4, 2.0
    A = S / 2 + np.logspace(-6, 2, 400_001) * S
    z = -1 / describing_function(A, S, J)
    g = z.real + z.imag ** 2 / (kc * ti)
    i = np.flatnonzero(np.sign(g[:-1]) != np.sign(g[1:]))
    assert i.size == 1
    i = int(i[0])
    a_star = A[i] - g[i] * (A[i + 1] - A[i]) / (g[i + 1] - g[i])
    w_star = -kc / (-1 / describing_function(a_star, S, J)).imag
    p = predict_limit_cycle(S, J, LEVEL_PI, LEVEL_PLANT)
    assert p.found and len(p.solutions) == 1 and p.solutions[0].stable
    assert p.amplitude == pytest.approx(a_star, rel=1e-5)
    assert p.omega == pytest.approx(w_star, rel=1e-5)
    assert p.period == pytest.approx(2 * np.pi / w_star, rel=1e-5)


def test_delay_loop_matches_dense_grid_minimum():
    """Concentration loop (dead time), undershoot S=5, J=2: minimum of |log(-N L)| over a dense grid."""
    S, J, kc, ti = 5.0, 2.0, 0.2, 10.0
    A = S / 2 + np.logspace(-3, 1, 1500) * S
    w = np.logspace(-3, 0, 1500)
    s = 1j * w
    L = kc * (1 + 1 / (ti * s)) * 3 * np.exp(-10 * s) / (10 * s + 1)  # written out independently here
    err = np.abs(np.log(-describing_function(A, S, J)[:, None] * L[None, :]))
    i, k = np.unravel_index(np.argmin(err), err.shape)
    p = predict_limit_cycle(S, J, CONC_PI, CONC_PLANT)
    assert p.found
    assert p.amplitude == pytest.approx(A[i], rel=1e-2)
    assert p.omega == pytest.approx(w[k], rel=1e-2)
    np.testing.assert_allclose(loop_frequency_response(w, CONC_PI, CONC_PLANT), L, rtol=1e-12)


def test_no_cycle_for_deadband_in_self_regulating_loop():
    # The 2003 paper: pure deadband in the concentration loop only adds dead time, no limit cycle.
    assert not predict_limit_cycle(5.0, 0.0, CONC_PI, CONC_PLANT).found
    assert not predict_limit_cycle(0.0, 0.0, LEVEL_PI, LEVEL_PLANT).found  # no friction at all


def test_cycle_of_a_linearly_unstable_loop_is_unstable():
    """With kc = 0.6 the linear concentration loop is unstable (it crosses the negative real axis left of
    -1). The backlash locus -1/N tends to -1 for large A, inside the encircled region, so the intersection
    is an unstable cycle (Loeb): reported among the solutions, but not as a prediction."""
    pi = (0.6, 10.0, 0.0, "reverse")
    w = np.logspace(-3, 0, 20_000)
    L = loop_frequency_response(w, pi, CONC_PLANT)
    k = np.flatnonzero((L.imag[:-1] < 0) & (L.imag[1:] >= 0))[0]
    assert L.real[k] < -1  # the Nyquist curve passes left of -1
    p = predict_limit_cycle(5.0, 0.0, pi, CONC_PLANT)
    assert not p.found and math.isnan(p.period)
    assert len(p.solutions) == 1 and not p.solutions[0].stable


def test_direct_action_and_characteristic_gain():
    # Direct action on a negative-gain plant is the same loop as reverse action on a positive one.
    p_rev = predict_limit_cycle(3.0, 1.5, LEVEL_PI, LEVEL_PLANT)
    p_dir = predict_limit_cycle(3.0, 1.5, (0.4, 2.0, 0.0, "direct"), ((-1.0,), (1.0, 0.0), 0.0))
    assert p_dir.found and p_dir.period == pytest.approx(p_rev.period, rel=1e-9)
    # A characteristic slope of 2 is the same loop as twice the controller gain.
    p_k = predict_limit_cycle(3.0, 1.5, LEVEL_PI, LEVEL_PLANT, characteristic_gain=2.0)
    p_2kc = predict_limit_cycle(3.0, 1.5, (0.8, 2.0, 0.0, "reverse"), LEVEL_PLANT)
    assert p_k.period == pytest.approx(p_2kc.period, rel=1e-9) and p_k.period != pytest.approx(p_rev.period)


@pytest.mark.parametrize(("controller", "plant", "message"), [
    ((0.0, 2.0, 0.0, "reverse"), LEVEL_PLANT, "kc"),
    ((0.4, -2.0, 0.0, "reverse"), LEVEL_PLANT, "ti"),
    ((0.4, 2.0, 0.0, "sideways"), LEVEL_PLANT, "action"),
    (LEVEL_PI, ((1.0,), (1.0, 0.0), -1.0), "delay"),
])
def test_predict_rejects_bad_loops(controller, plant, message):
    with pytest.raises(ValueError, match=message):
        predict_limit_cycle(3.0, 1.5, controller, plant)


# --------------------------------------------------------------------------- prediction vs simulation

def simulate_level_loop(S: float, J: float, *, dt: float = 0.01, duration: float = 400.0):
    """Level loop of the 2003 paper, stepped per sample in the design's loop order: PV_k measured, OP_k from
    a PI (e = sp - pv, Euler integral), MV_k from the stiction bank, PV integrates MV - u0 over [t_k, t_k+dt).
    Starts 1 unit below the set point with the valve at rest at the bias."""
    kc, ti, bias = 0.4, 2.0, 50.0
    bank = StictionBank(1, S=S, J=J, model="kano")
    bank.reset(np.array([bias]))
    n = int(round(duration / dt))
    op = np.empty(n)
    pv, integral, u = -1.0, 0.0, np.empty(1)
    for k in range(n):
        e = 0.0 - pv
        integral += dt * e / ti
        u[0] = bias + kc * (e + integral)
        mv = bank.step(u)[0]
        op[k] = u[0]
        pv += dt * (mv - bias)
    return dt * np.arange(n), op


@pytest.mark.parametrize("J", [0.0, 1.5])  # pure deadband; the 2003 paper's undershoot case S=3, J=1.5
def test_level_loop_prediction_agrees_with_simulation(J):
    S = 3.0
    p = predict_limit_cycle(S, J, LEVEL_PI, LEVEL_PLANT)
    t, op = simulate_level_loop(S, J)
    lc = measure_limit_cycle(t, op)
    assert p.found and lc.sustained  # with an integrating plant even a pure deadband cycles
    assert p.period == pytest.approx(lc.period, rel=0.10)
    assert p.amplitude == pytest.approx(lc.amplitude, rel=0.15)
