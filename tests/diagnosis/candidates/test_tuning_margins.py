"""The tuning candidate's arithmetic: the PI read from OP (at once or one sample late) and the loop's margins."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import brentq, minimize_scalar

from valve_emulator.benchmark.independent import (
    FAMILIES,
    Plant,
    draw,
    loop_margins,
)
from valve_emulator.diagnosis.assess.ring import ring_check
from valve_emulator.diagnosis.candidates.tuning import identify_pi, nominal_margins

RNG = np.random.default_rng(7)


def _pi_output(pv: np.ndarray, sp: np.ndarray, kc: float, ti: float, dt: float, lag: int) -> np.ndarray:
    """A positional PI on SP_k − PV_{k−lag}, OP = 50 at the start."""
    seen = np.concatenate([pv[:lag], pv[:pv.size - lag]])
    e = sp - seen
    return 50.0 + kc * (e + np.cumsum(e) * dt / ti)


@pytest.mark.parametrize("lag", [0, 1])
def test_identify_pi_finds_the_controller_and_whether_it_acts_one_sample_late(lag):
    dt, n = 1.0, 2000
    pv = np.cumsum(RNG.normal(size=n)) * 0.05 + RNG.normal(size=n)
    sp = np.where(np.arange(n) % 400 < 200, 1.0, -1.0)        # set-point steps, as a DCS records them
    op = _pi_output(pv, sp, 0.8, 20.0, dt, lag)
    kc, ti, r2, found = identify_pi(op, pv, sp, dt)
    assert found == lag
    assert (kc, ti) == (pytest.approx(0.8), pytest.approx(20.0)) and r2 > 0.999


def test_margins_of_a_delayed_integrator_under_p_control_are_the_textbook_ones():
    # L = kc·K/s·e^{−θs}: phase −90° − ωθ reaches −180° at ω = π/(2θ), so GM = π/(2·kc·K·θ);
    # |L| = 1 at ω = kc·K, so PM = 90° − kc·K·θ in degrees.
    kc, K, theta = 0.5, 0.02, 20.0
    m = nominal_margins([K], [1.0, 0.0], theta, kc, None, 0.0, action="reverse", extra_delay=0.0)
    assert m.gain_margin == pytest.approx(math.pi / (2.0 * kc * K * theta), rel=1e-3)
    assert m.phase_margin == pytest.approx(90.0 - math.degrees(kc * K * theta), rel=1e-3)


def test_margins_of_a_loop_whose_phase_starts_below_minus_180_degrees_are_on_the_right_branch():
    # A PI on a double integrator with a lead, K(1 + sT)/s²·e^{−θs}: three integrators, so the phase starts near
    # −270°, which np.angle reads as +90°. Margins from the textbook phase −270° + atan(ωTi) + atan(ωT) − ωθ:
    # PM at |L| = 1, GM where the phase falls back through −180° (the loop is conditionally stable).
    kc, ti, K, T, theta = 1.0, 40.0, 0.004, 20.0, 1.0

    def loop(w):
        s = 1j * w
        return kc * (1.0 + 1.0 / (ti * s)) * K * (1.0 + s * T) / s**2 * np.exp(-s * theta)

    def phase(w):
        return -270.0 + math.degrees(math.atan(w * ti) + math.atan(w * T) - w * theta)

    wc = brentq(lambda w: abs(loop(w)) - 1.0, 1e-4, 10.0)
    top = minimize_scalar(lambda w: -phase(w), bounds=(1e-3, 10.0), method="bounded").x
    wg = brentq(lambda w: phase(w) + 180.0, top, 10.0)
    m = nominal_margins([K * T, K], [1.0, 0.0, 0.0], theta, kc, ti, 0.0, action="reverse", extra_delay=0.0)
    assert m.phase_margin == pytest.approx(180.0 + phase(wc), rel=1e-3)
    assert m.gain_margin == pytest.approx(1.0 / abs(loop(wg)), rel=1e-3)


def test_margins_need_negative_feedback():
    assert nominal_margins([2.0], [10.0, 1.0], 3.0, 1.0, 10.0, 0.0, action="direct", extra_delay=1.5) is None
    assert nominal_margins([-2.0], [10.0, 1.0], 3.0, 1.0, 10.0, 0.0, action="direct", extra_delay=1.5) is not None


@pytest.mark.parametrize("index", range(6))
def test_nominal_margins_agree_with_the_independent_simulators_truth(index):
    rec, truth, nominal = draw("aggressive_pi", np.random.default_rng([3, list(FAMILIES).index("aggressive_pi"),
                                                                     index]))
    p, c = nominal["plant"], nominal["controller"]
    m = nominal_margins(p["num"], p["den"], p["delay"], c["kc"], c["ti"], 0.0, action=c["action"],
                        extra_delay=truth["margins_extra_delay"])
    t = truth["margins"]
    assert m.ms == pytest.approx(t["Ms"], rel=0.01)
    assert m.gain_margin == pytest.approx(t["GM"], rel=0.01)
    assert m.phase_margin == pytest.approx(t["PM"], rel=0.01)
    assert m.aggressive                                      # gain margins 1.2–1.6 are aggressive


def test_a_simc_tuned_loop_is_not_aggressive():
    plant = Plant(kind="fopdt", gain=1.5, tau=20.0, delay=4.0)
    kc, ti = 20.0 / (1.5 * 2 * 5.5), 20.0                        # SIMC with τc = θ_eff = 5.5 s
    m = nominal_margins([1.5], [20.0, 1.0], 4.0, kc, ti, 0.0, action="reverse", extra_delay=1.5)
    assert not m.aggressive and m.ms == pytest.approx(loop_margins(plant, kc, ti, 1.5)["Ms"], rel=0.01)


def _judged(rec):
    kc, ti, _, lag = identify_pi(rec.op, rec.pv, rec.sp, rec.dt)
    return ring_check(rec.op, rec.pv, rec.sp, kc, ti, rec.dt, lag)


def test_an_aggressive_linear_loop_rings_no_more_regularly_than_its_identified_loop():
    """Known truth: a healthy valve under a PI tuned to a gain margin of 1.2–1.6 (the independent simulator's
    ``aggressive_pi``, a filtered random load) rings, and its record is never beyond what the ARX loop makes."""
    for i in range(6):
        rec, _, _ = draw("aggressive_pi", np.random.default_rng([5, list(FAMILIES).index("aggressive_pi"), i]))
        check = _judged(rec)
        assert check is not None and not check.beyond, (i, check)


def test_a_sticky_valves_limit_cycle_is_beyond_the_ring_of_the_loop_identified_on_it():
    """A sticky level loop of the independent simulator (an integrator with a 2.5 s lag and a 3.4 s dead time, a
    PI acting one sample late, S 3.98 %, J 4.07 %: draw 32.19 of the level property test, the record the test
    was written for) cycles with r ≈ 81; the ARX loop identified on it, under its own PI, rings at most at
    r ≈ 22 in the 99 records simulated."""
    rec, truth, _ = draw("level_sticky", np.random.default_rng([32, 19]))
    assert truth["sticky"] and truth["plant"]["kind"] == "integrating_lag"
    check = _judged(rec)
    assert check is not None and check.beyond, check
    assert check.regularity > 3.0 * check.simulated
