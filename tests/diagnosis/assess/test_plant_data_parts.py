"""The parts of the plant-data path, each against a known truth: refusals, resampling, the new candidates."""

from __future__ import annotations

import numpy as np
import pytest
from historian import flow_limited_loop

from valve_emulator.diagnosis.assess.adequacy import EXCITATION, adequacy, longest_constant_run
from valve_emulator.diagnosis.assess.decision import assess
from valve_emulator.diagnosis.candidates import KINDS, SLOTS, ChainContext, get, registry
from valve_emulator.diagnosis.candidates.quantization import on_few_levels, quantum
from valve_emulator.diagnosis.candidates.saturation import op_flat_at_extreme
from valve_emulator.diagnosis.candidates.tuning import identify_pi, loop_response
from valve_emulator.diagnosis.fit.backfit import backfit
from valve_emulator.diagnosis.fit.frame import noise_sigma
from valve_emulator.diagnosis.fit.linear import LinearStructure
from valve_emulator.recordings.recording import Recording, RecordingError
from valve_emulator.recordings.resample import regularize

RNG = np.random.default_rng(7)


def _rec(op, pv, *, dt=1.0, sp=None, t=None, name="r") -> Recording:
    t = dt * np.arange(len(op)) if t is None else t
    return Recording(t, sp, op, None, pv, source=name)


# ------------------------------------------------------------------------------------------- "cannot tell"

def test_too_short_a_record_cannot_tell_and_says_how_many_samples():
    a = assess(_rec(50 + RNG.normal(size=150), RNG.normal(size=150)))
    assert a.decision == "cannot_tell" and a.explanation is None
    assert "150 samples" in a.reason and "at least 200" in a.reason


def test_a_flat_pv_while_op_winds_up_is_no_response_and_names_the_look_alikes():
    op = np.linspace(5.0, 80.0, 600)              # OP winds up
    pv = np.r_[np.linspace(0.3, 0.0, 100), np.zeros(500)]   # flow stops at zero and stays there
    a = assess(_rec(op, pv))
    assert a.decision == "no_response"
    assert "PV is flat" in a.reason and "84 % of the record" in a.reason and "seized valve" in a.reason
    assert a.adequacy.facts["pv_flat_share"] == pytest.approx(501 / 600)   # the last ramp sample is 0 too


def test_no_oscillation_and_no_excitation_cannot_tell():
    op = 40 + 0.1 * RNG.normal(size=800)          # OP only dithers, no set point change, no cycle
    pv = 50 + RNG.normal(size=800)
    a = assess(_rec(op, pv, sp=np.full(800, 50.0)))
    assert a.decision == "cannot_tell"
    assert "no oscillation" in a.reason and "no excitation" in a.reason
    assert a.adequacy.facts["op_range_in_noise"] < EXCITATION


def test_a_set_point_change_or_a_cycle_counts_as_information():
    op = 40 + 0.1 * RNG.normal(size=800)
    sp = np.r_[np.full(400, 50.0), np.full(400, 51.0)]
    assert adequacy(_rec(op, 50 + RNG.normal(size=800), sp=sp)).ok
    k = np.arange(800)
    cyc = adequacy(_rec(40 + np.sin(2 * np.pi * k / 50) + 0.1 * RNG.normal(size=800), np.cos(2 * np.pi * k / 50)))
    assert cyc.ok and cyc.facts["oscillating"] and cyc.facts["period"] == pytest.approx(50.0, rel=0.05)


def test_noise_and_runs_known_truth():
    assert noise_sigma(np.cumsum(RNG.normal(scale=0.2, size=20000))) == pytest.approx(0.2 / np.sqrt(2), rel=0.05)
    assert longest_constant_run(np.array([1.0, 1.0, 2.0, 2.0, 2.0, 3.0])) == 3


# ------------------------------------------------------------------------------------------------- resampling

def test_a_jittered_series_is_put_on_the_grid_op_held_pv_interpolated():
    t = np.arange(400, dtype=float)
    t[1::7] += 0.2                                # every 7th row came a tick late (1.2 s then 0.8 s)
    op = np.floor(t / 10.0)                       # OP written every 10 s: a staircase
    pv = 2.0 * t                                  # a ramp
    rec, note = regularize(_rec(op, pv, t=t))
    assert np.allclose(np.diff(rec.t), 1.0) and rec.t[0] == 0.0
    np.testing.assert_allclose(rec.pv, 2.0 * rec.t)               # linear in, linear out
    last = np.searchsorted(t, rec.t, side="right") - 1             # ZOH: the last row at or before each time
    np.testing.assert_array_equal(rec.op, op[last])
    assert rec.op[50] == 4.0 and op[50] == 5.0   # the row of t = 50 came at 50.2 s: at 50 s OP was still 4
    # each late row: 1.2 s then 0.8 s
    assert note.startswith("resampled onto a uniform 1 s grid") and "114 of 399 steps" in note


def test_a_uniform_series_is_left_alone_and_a_real_gap_is_refused_with_its_line():
    rec = _rec(np.zeros(50), np.arange(50.0))
    same, note = regularize(rec)
    assert same is rec and note is None
    t = np.r_[np.arange(20.0), 25.0 + np.arange(30.0)]   # a 6 s hole in a 1 s series
    with pytest.raises(RecordingError, match=r"r: line 22: a gap of 6 s after t = 19 s"):
        regularize(_rec(np.zeros(50), np.zeros(50), t=t))


# --------------------------------------------------------------------------------------------- new candidates

def test_the_new_candidates_are_registered_with_their_kinds():
    lib = registry()
    expected = {"saturation": ("limit", "chain"), "quantization": ("output", "output"),
                "disturbance": ("output", "output"), "tuning": ("loop", "loop")}
    for name, (slot, kind) in expected.items():
        cand = lib[name]
        assert cand.slot == slot and cand.kind == kind and slot in SLOTS and slot in KINDS[kind]


def test_saturation_clips_the_flow_at_its_limit_and_its_grid_stays_inside_the_data():
    op = np.linspace(10.0, 90.0, 200)
    ctx = ChainContext(dt=1.0, op=op, op_span=80.0)
    sat = get("saturation")
    out = sat.apply(op, np.array([[0.0, 60.0], [30.0, 100.0]]), ctx)
    np.testing.assert_array_equal(out[:, 0], np.minimum(op, 60.0))
    np.testing.assert_array_equal(out[:, 1], np.maximum(op, 30.0))
    g = sat.grid(ctx)
    assert g.shape[1] == 2 and np.all((g[:, 0] > 0) ^ (g[:, 1] < 100))      # one-sided rows only
    assert g[:, 0].max() < np.percentile(op, 50) and g[:, 1][g[:, 1] < 100].min() > np.percentile(op, 50)
    assert sat.parameters(np.array([0.0, 72.5])) == {"lo": None, "hi": 72.5}


@pytest.mark.parametrize("scale, offset", [(0.16, 4.0), (1.0, 0.0), (276.48, 0.0), (0.01, -0.5)])
def test_op_flat_at_an_extreme_is_told_in_any_units(scale, offset):
    _, clamped, _ = flow_limited_loop(70.0, 90.0, (40, 60, 35, 85, 45, 30, 55, 40))
    _, free, _ = flow_limited_loop(100.0, 100.0, (40, 55, 35, 52, 45, 30))
    assert op_flat_at_extreme(offset + scale * clamped)
    assert op_flat_at_extreme(offset - scale * clamped)   # held at the low limit (a reverse-acting export)
    assert not op_flat_at_extreme(offset + scale * free)
    assert not op_flat_at_extreme(np.full(100, offset))


@pytest.mark.slow
def test_saturation_is_searched_without_a_span_once_op_sits_flat_at_an_extreme():
    # OP exported in mA (4-20 mA, span not given): the flow limit at 70 % travel is found, in mA, because the
    # controller output sat at its 90 % clamp; the same kind of loop that never reaches a limit is not offered
    # saturation at all (no span, no flat extreme).
    sp, op, pv = flow_limited_loop(70.0, 90.0, (40, 60, 35, 85, 45, 30, 55, 40))
    a = assess(_rec(4.0 + 0.16 * op, pv, sp=sp))
    found = {f.physics: f for f in a.explanation.findings}
    assert "saturation" in found, a.reason
    assert found["saturation"].parameters["hi"] == pytest.approx(4.0 + 0.16 * 70.0, abs=0.16 * 2.0)
    assert "OP units" in found["saturation"].description and "% travel" not in found["saturation"].description
    sp, op, pv = flow_limited_loop(100.0, 100.0, (40, 55, 35, 52, 45, 30))
    b = assess(_rec(4.0 + 0.16 * op, pv, sp=sp))
    assert "saturation" not in {r.option for r in b.explanation.ranking}


def test_quantization_applies_only_to_a_pv_on_few_levels():
    smooth = np.sin(np.linspace(0, 20, 1000)) + 0.01 * RNG.normal(size=1000)
    assert not on_few_levels(smooth)
    stairs = 0.5 * np.round(smooth / 0.5)
    assert on_few_levels(stairs) and quantum(stairs) == pytest.approx(0.5)
    held = np.repeat(RNG.normal(size=100), 10)   # an archive that holds values: continuous levels, held
    assert on_few_levels(held)


def test_quantization_targets_the_nearest_point_of_each_readings_interval():
    q = get("quantization")
    pv = np.array([0.0, 1.0, 1.0, 2.0])
    ctx = ChainContext(dt=1.0, op=np.zeros(4), op_span=1.0, pv=pv, y_scale=1.0, y_mean=0.0, window=(0, 4))
    target, _ = q.adjust(pv, np.array([0.3, 1.2, 2.0, 2.1]), np.array([1.0]), ctx)
    np.testing.assert_allclose(target, [0.3, 1.2, 1.5, 2.1])   # within ±0.5 of the reading: unchanged


def test_disturbance_is_fitted_jointly_with_the_linear_part_known_truth():
    # PV = 2 u(k-4) (a static gain; the model is q^-1 plus a dead time of 3 samples) + 0.7 sin(2πk/40 + 0.4):
    # u correlated with the cycle.
    T = 1200
    k = np.arange(T)
    u = 50 + 3 * np.sin(2 * np.pi * k / 40 + 1.0) + np.cumsum(RNG.normal(scale=0.3, size=T))
    y = 2.0 * np.r_[np.full(4, u[0]), u[:-4]] + 0.7 * np.sin(2 * np.pi * k / 40 + 0.4)
    ctx = ChainContext(dt=1.0, op=u, op_span=10.0, pv=y, y_scale=1.0, y_mean=0.0, window=(50, T))
    dist = get("disturbance")
    assert 40.0 in np.round(dist.grid(ctx)[:, 0], 0)            # the periodogram offers the period
    bf = backfit(u, y, (50, T), LinearStructure(delay=3.0), 1.0, dist, np.array([40.0, 0.0, 0.0]), ctx)
    assert bf.fit.sse < 1e-12 * T
    assert bf.params[1] == pytest.approx(0.7, rel=1e-6) and bf.params[2] == pytest.approx(0.4, abs=1e-6)
    assert bf.level.gain == pytest.approx(2.0, rel=1e-6)


def test_pi_identification_and_loop_sensitivity_known_truth():
    dt, T = 1.0, 3000
    e = RNG.normal(size=T).cumsum() * 0.05 + RNG.normal(size=T)
    kc, ti = 0.8, 20.0
    op = 50 + np.cumsum(kc * np.diff(e, prepend=e[0]) + kc * dt / ti * e)
    k, t, r2, lag = identify_pi(op, -e, None, dt)      # e = SP - PV with SP = 0
    assert (k, t) == (pytest.approx(kc), pytest.approx(ti)) and r2 > 0.999 and lag == 0
    # A pure integrator 1/s with P control Kc: L = Kc/(jω) → |S| < 1 at low frequencies, peak ~ 1 far away.
    w = np.geomspace(1e-3, 1.0, 200)
    L = loop_response(0.1, float("inf"), 0.01, 1.0, (), 0.0, True, w)
    assert np.all(np.abs(1.0 / (1.0 + L)) < 1.05)
