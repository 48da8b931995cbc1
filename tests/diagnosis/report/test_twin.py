"""The twin (``Diagnosis.to_config``): the loop a diagnosis found, as a loop config that replays the recording.

Known truth throughout: closed loops simulated with concealed physics (the proof cases of
:mod:`valve_emulator.benchmark.cases`, short runs), diagnosed against their nominal models or as plant data.
"""

import dataclasses
import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from stroke_rate import TOY, StrokeRate, slow_valve

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.benchmark.independent import draw
from valve_emulator.config import loop_from_mapping
from valve_emulator.config.loader import load_loop
from valve_emulator.config.writer import write_loop
from valve_emulator.diagnosis.api import diagnose
from valve_emulator.diagnosis.candidates import base, register
from valve_emulator.diagnosis.fit.continuous import continuous_transfer_function
from valve_emulator.diagnosis.fit.data import fit_percent
from valve_emulator.diagnosis.fit.linear import LinearStructure, fit_one
from valve_emulator.diagnosis.fit.nominal import Nominal, replay_plant
from valve_emulator.diagnosis.report.twin import identify_pi, replay_fit
from valve_emulator.recordings.recording import Recording
from valve_emulator.simulation.limit_cycle import measure_limit_cycle
from valve_emulator.simulation.loop import simulate_loop
from valve_emulator.simulation.replay import replay_op, replay_sp

BY_NAME = {c.name: c for c in CASES}


@functools.cache
def with_sp(name: str, duration: float) -> tuple[Recording, object]:
    """A proof case's concealed recording, but with its set point kept, and its nominal model."""
    case = BY_NAME[name]
    _, nominal, true = generate(case, duration=duration)
    run = simulate_loop(true)
    k = int(round(case.cut / run.dt))
    rec = Recording(run.t[k:] - run.t[k], run.sp[k:], run.op[k:], None, run.pv[k:], source=case.name)
    return rec, nominal


@functools.cache
def diagnosed(name: str, duration: float):
    """``(recording, nominal, diagnosis)`` of a proof case with its SP kept, against its nominal model (cached:
    several tests look at the same one; with a model the diagnosis reads only t, OP and PV)."""
    rec, nominal = with_sp(name, duration)
    return rec, nominal, diagnose(rec, nominal)


@pytest.mark.parametrize("num, den, delay, structure", [
    ([3.0], [10.0, 1.0], 10.0, LinearStructure(taus=(10.0,), delay=10.0)),
    ([2.0, 1.0], [20.0, 9.0, 1.0], 3.0, LinearStructure(taus=(4.0, 5.0), delay=3.0)),
    ([1.0], [1.0, 0.0], 0.0, LinearStructure(integrating=True)),
    ([1.0], [4.0, 1.0, 0.0], 2.0, LinearStructure(taus=(4.0,), integrating=True, delay=2.0)),
], ids=["fopdt", "second order with a zero", "integrator", "integrator with a lag"])
def test_the_fitted_linear_part_comes_back_as_the_true_transfer_function(num, den, delay, structure):
    """Simulate a known plant exactly (ZOH), fit its taps with the true poles, undo the hold: the transfer
    function returns (monic denominator)."""
    rng = np.random.default_rng(3)
    u = 50.0 + np.cumsum(rng.normal(size=600)) * 0.3
    y = replay_plant(Nominal(structure, True, tuple(num), tuple(den)), u, 1.0)
    fit = fit_one(u, y, (40, 600), structure, 1.0)
    got_num, got_den = continuous_transfer_function(structure, fit.taps, 1.0)
    lead = den[0]
    np.testing.assert_allclose(got_den, np.asarray(den) / lead, atol=1e-9)
    want = np.asarray(num) / lead
    want = np.concatenate([np.zeros(len(got_num) - want.size), want])   # a fitted zero may leave a tiny s-term
    np.testing.assert_allclose(got_num, want, rtol=1e-5, atol=1e-5)


def whole_record_fits(d, rec: Recording, cfg) -> tuple[float, float]:
    """``(diagnosis, twin)``: the whole-record fit (%) of the diagnosis' prediction on the recorded OP and of the
    twin's open-loop replay, every sample from the first."""
    return fit_percent(rec.pv, d.predict(rec.op)), fit_percent(rec.pv, replay_op(cfg, rec).pv)


@pytest.mark.parametrize("name, duration", [
    ("stiction, undershoot", 1500.0), ("stiction, no offset", 1500.0), ("stiction, overshoot", 1500.0),
    ("stiction, level loop", 400.0), ("actuator lag", 1200.0), ("equal-percentage characteristic", 1200.0)])
def test_the_open_loop_replay_fits_as_well_as_the_diagnosis(name, duration):
    """Acceptance: the twin, written and read back, driven by the recorded OP, fits the held-out part within
    2 points of ``fit_after`` (the same samples; the twin is the fitted model, so it should), and the whole
    record from its first sample at least as well as the diagnosis' own prediction, less 2 points: the twin
    starts in the state the fit started in (a sticky valve started elsewhere can stay stuck for long)."""
    rec, _, d = diagnosed(name, duration)
    twin = d.twin()
    cfg = loop_from_mapping(__import__("yaml").safe_load(twin.text()))
    assert cfg == dataclasses.replace(twin.config, source="<mapping>")
    fit = replay_fit(d, replay_op(cfg, rec).pv)
    assert abs(fit - d.fit_after) <= 2.0, (fit, d.fit_after)
    diagnosis, replay = whole_record_fits(d, rec, cfg)
    assert replay >= diagnosis - 2.0, (replay, diagnosis)
    assert set(BY_NAME[name].truth) <= {f.physics for f in d.findings}   # the concealed physics was found


#: Independent closed loops whose every finding the loop config can express (no quantised PV): (family, seed,
#: with the nominal model). Among them an actuator lag before a sticky valve or a deadband, and a flow limit
#: behind a sticky valve.
UNSEEN = [(family, seed, with_model) for family in ("flow_sticky", "healthy_flow", "level_sticky", "slow_noisy_valve")
          for seed in range(3) for with_model in (True, False)]


@functools.cache
def unseen(family: str, seed: int, with_model: bool):
    rec, _, mapping = draw(family, np.random.default_rng(seed))
    return rec, diagnose(rec, loop_from_mapping(mapping) if with_model else None)


@pytest.mark.slow
@pytest.mark.parametrize(("family", "seed", "with_model"), UNSEEN,
                         ids=lambda v: ("model" if v else "plant") if isinstance(v, bool) else str(v))
def test_twins_of_loops_the_package_did_not_simulate_replay_the_whole_record_as_their_diagnosis(family, seed,
                                                                                                 with_model):
    """Recordings of the independent simulator (continuous plants, the controller a sample late, friction and
    lag in either order): the twin's open-loop replay fits the whole record at least as well as the diagnosis'
    prediction, less 2 points (each of the 24 loops; a diagnosis of a few seconds each)."""
    rec, d = unseen(family, seed, with_model)
    diagnosis, replay = whole_record_fits(d, rec, d.to_config())
    assert replay >= diagnosis - 2.0, (round(diagnosis, 1), round(replay, 1))


@pytest.mark.slow
def test_a_found_actuator_lag_and_saturation_sit_where_the_fit_had_them():
    """An independent flow loop (with its model) whose diagnosis finds an actuator lag before a sticky valve and
    a saturation: the twin writes the lag as ``valve.actuator_lag`` (before the friction), not into the plant,
    and the saturation as ``valve.flow_limits`` (after the characteristic), not as the controller's op_limits;
    so its replay is the diagnosis' prediction (within 0.5 points over the whole record)."""
    rec, d = unseen("flow_sticky", 1, True)
    found = {f.physics for f in d.findings}
    assert {"actuator_lag", "saturation", "stiction"} <= found, found
    cfg = d.to_config()
    fitted = d.explanation.fitted
    assert cfg.valve.actuator_lag == pytest.approx(float(fitted.active["actuator"].params[0]))
    lo, hi = (float(x) for x in fitted.active["limit"].params)
    assert cfg.valve.flow_limits == pytest.approx((max(lo, 0.0), min(hi, 100.0)))
    assert cfg.controller.op_limits == (0.0, 100.0)
    assert len(cfg.plant.den) == len(continuous_transfer_function(fitted.linear.structure, fitted.linear.taps,
                                                                  rec.dt)[1])   # no lag factor in the plant
    diagnosis, replay = whole_record_fits(d, rec, cfg)
    assert replay == pytest.approx(diagnosis, abs=0.5)
    assert any(line.startswith("valve.actuator_lag:") for line in d.twin().provenance)
    assert any(line.startswith("valve.flow_limits:") for line in d.twin().provenance)


def served_pv_after(cfg, seconds: float, tmp_path) -> float:
    """PV of the twin served by the emulated device (Modbus TCP, the testing kit's manual clock), ``seconds``
    after it starts."""
    from valve_emulator.testing import Emulator

    path = tmp_path / "twin.yaml"
    write_loop(cfg, path)
    with Emulator(str(path), clock="manual") as emu:
        emu.advance(seconds)
        return emu.state()["pv_f32"]


@pytest.mark.parametrize("source", [("case", "stiction, undershoot", 1500.0), ("case", "stiction, overshoot", 1500.0),
                                    ("unseen", "flow_sticky", 0), ("unseen", "healthy_flow", 1)],
                         ids=lambda s: f"{s[1]}")
def test_a_served_twin_starts_at_the_recordings_operating_point(source, tmp_path):
    """``serve TWIN``: one second after start the device's PV lies in the recording's first second (widened by
    the twin's noise, which the served twin leaves out here so that the start is what is tested)."""
    kind, name, arg = source
    if kind == "case":
        rec, _, d = diagnosed(name, arg)
    else:
        rec, d = unseen(name, arg, True)
    cfg = d.to_config()
    quiet = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, noise=0.0))
    pv = served_pv_after(quiet, 1.0, tmp_path)
    first = rec.pv[rec.t - rec.t[0] <= 1.0 + 1e-9]
    assert first.min() - cfg.plant.noise <= pv <= first.max() + cfg.plant.noise, (pv, first, cfg.plant.noise)


def test_the_twin_carries_the_found_physics_in_travel_units():
    rec, nominal, d = diagnosed("stiction, undershoot", 1500.0)
    cfg = d.to_config(name="fic101")
    assert cfg.name == "fic101"
    found = [cfg.valve.S, cfg.valve.J]
    assert found == pytest.approx([5.0, 2.0], abs=0.3)
    assert cfg.plant.num[-1] / cfg.plant.den[-1] == pytest.approx(3.0, rel=0.05)   # the concealed plant's gain
    assert (cfg.controller.kc, cfg.controller.ti) == (nominal.controller.kc, nominal.controller.ti)
    assert cfg.simulation.dt == cfg.device.tick == rec.dt


def test_a_found_actuator_lag_is_the_twins_actuator_not_a_plant_lag():
    """The concealed actuator lag (τ = 4 s) comes back as ``valve.actuator_lag``; the plant keeps the fitted
    linear part's first-order denominator."""
    _, _, d = diagnosed("actuator lag", 1200.0)
    cfg = d.to_config()
    assert cfg.valve.actuator_lag == pytest.approx(4.0, rel=0.25)
    assert len(cfg.plant.den) == 2


@pytest.mark.parametrize("name, duration", [("stiction, undershoot", 1500.0), ("stiction, level loop", 400.0)])
def test_the_closed_loop_replay_keeps_the_limit_cycle(name, duration):
    """Acceptance: the twin in closed loop on the recorded SP cycles with the recording's period and PV amplitude,
    each within 20 %. The measurement noise decides when a sticky valve slips, so a short record's cycle varies
    from one noise realisation to the next: the twin's median over three noise seeds is compared."""
    rec, _, d = diagnosed(name, duration)
    cfg = d.to_config()
    want = measure_limit_cycle(rec.t, rec.pv)
    runs = [replay_sp(dataclasses.replace(cfg, simulation=dataclasses.replace(cfg.simulation, seed=seed)), rec)
            for seed in range(3)]
    got = [measure_limit_cycle(sim.t, sim.pv) for sim in runs]
    assert want.sustained and all(g.sustained for g in got)
    assert np.median([g.period for g in got]) == pytest.approx(want.period, rel=0.2)
    assert np.median([g.amplitude for g in got]) == pytest.approx(want.amplitude, rel=0.2)


@pytest.mark.parametrize("kc, ti, action", [(0.4, 2.0, "reverse"), (1.3, 25.0, "direct"), (0.7, None, "reverse")])
def test_a_pi_is_recovered_from_sp_pv_and_op(kc, ti, action):
    mapping = {"name": "pi", "valve": {"S": 2.0, "J": 1.0},
               "plant": {"num": [1.0 if action == "reverse" else -1.0], "den": [8.0, 1.0], "delay": 1.0,
                         "noise": 0.05},
               "controller": {"kc": kc, "ti": ti, "action": action, "sp_steps": [[5.0, 3.0], [80.0, -2.0]]},
               "simulation": {"dt": 0.5, "duration": 200.0, "seed": 2}}
    run = simulate_loop(loop_from_mapping(mapping))
    got_kc, got_ti, got_action = identify_pi(run.t, run.sp, run.pv, run.op)
    assert got_action == action and got_kc == pytest.approx(kc, rel=1e-3)
    assert (got_ti is None) if ti is None else got_ti == pytest.approx(ti, rel=1e-3)


def test_plant_data_with_a_set_point_gets_the_identified_pi_in_the_twins_units():
    """Without a model the twin's travel is the diagnosis' unit-free frame; the PI found from SP, PV and OP is in
    it, and op_range maps the recorded OP onto it."""
    rec, _ = with_sp("stiction, level loop", 400.0)
    scaled = Recording(rec.t, rec.sp, 4000.0 + 236.48 * rec.op, None, rec.pv, source="counts")   # raw counts
    cfg = diagnose(scaled).to_config()
    lo, hi = cfg.valve.op_range
    per_travel = (hi - lo) / 100.0 / 236.48          # % travel of the recording per % of the twin's travel
    assert cfg.controller.mode == "auto" and cfg.controller.action == "reverse"
    assert cfg.controller.kc * per_travel == pytest.approx(0.4, rel=1e-3)   # the true kc, in % travel per m
    assert cfg.controller.ti == pytest.approx(2.0, rel=1e-3)
    assert cfg.valve.S * per_travel == pytest.approx(3.0, rel=0.15)


def test_without_a_set_point_or_a_controller_to_copy_the_controller_is_manual():
    rec, nominal, _ = diagnosed("stiction, level loop", 400.0)
    no_sp = Recording(rec.t, None, rec.op, None, rec.pv, source=rec.source)
    twin = diagnose(no_sp, dataclasses.replace(nominal, controller=None)).twin()
    c = twin.config.controller
    assert c.mode == "manual" and c.bias == pytest.approx(twin.config.valve.op0)
    assert any("manual" in line for line in twin.provenance)


def test_no_fitted_model_no_twin():
    t = np.arange(400.0)
    rec = Recording(t, None, 50.0 + 0.0 * t, None, np.sin(t / 7.0), source="flat.csv")
    d = diagnose(rec)
    with pytest.raises(ValueError, match="flat.csv"):
        d.to_config()


def test_the_twin_file_says_where_each_number_came_from(tmp_path):
    twin = diagnosed("actuator lag", 1200.0)[2].twin()
    path = tmp_path / "twin.yaml"
    path.write_text(twin.text(), encoding="utf-8")
    header = [line for line in path.read_text(encoding="utf-8").splitlines() if line.startswith("#")]
    for key in ("valve.S", "plant.num", "controller", "op_range", "actuator lag"):
        assert any(key in line for line in header), key
    assert dataclasses.replace(load_loop(path), source="") == dataclasses.replace(twin.config, source="")


@functools.cache
def plant_twin(a: float = 1.0, b: float = 0.0, c: float = 1.0, d: float = 0.0):
    """The twin of the level loop's plant data (with SP) after OP -> a·OP + b and PV, SP -> c·PV + d."""
    rec, _ = with_sp("stiction, level loop", 300.0)
    mapped = Recording(rec.t, c * rec.sp + d, a * rec.op + b, None, c * rec.pv + d, source="mapped")
    return diagnose(mapped).to_config()


@pytest.mark.slow
@settings(max_examples=2, deadline=None, derandomize=True)
@given(a=st.floats(0.01, 300.0), b=st.floats(-5e3, 5e3), c=st.floats(0.05, 20.0), d=st.floats(-1e3, 1e3))
def test_the_twin_moves_with_the_units_of_op_and_pv(a, b, c, d):
    """Without a model the twin's travel is the unit-free frame: S, J and the plant's dynamics stay put while
    op_range follows OP's map; the plant's gain, pv0, noise and the controller's kc follow PV's."""
    ref, got = plant_twin(), plant_twin(a, b, c, d)
    friction = [got.valve.S, got.valve.J]
    assert friction == pytest.approx([ref.valve.S, ref.valve.J], rel=0.02, abs=0.05)
    assert got.valve.op_range == pytest.approx([a * x + b for x in ref.valve.op_range], rel=1e-6, abs=1e-6)
    assert got.plant.den == pytest.approx(ref.plant.den, rel=0.02)
    assert got.plant.num[-1] == pytest.approx(c * ref.plant.num[-1], rel=0.02)
    assert got.plant.pv0 == pytest.approx(c * ref.plant.pv0 + d, rel=0.02, abs=0.02 * c)
    assert got.controller.kc == pytest.approx(ref.controller.kc / c, rel=0.01)
    assert got.controller.ti == pytest.approx(ref.controller.ti, rel=0.01)


def test_an_external_disturbance_becomes_the_input_sinusoid_that_makes_it():
    """Known truth: a load sinusoid of 3 % flow, period 180 s, phase 0.3 rad at t = 0 of the run, enters a linear
    loop with set-point steps. On plant data the diagnosis finds a sinusoid in PV; the twin's plant input gets the
    one the plant turns into it — the true one — and replays as the diagnosis' model predicts."""
    steps = [[100.0 + 150.0 * i, float(v)] for i, v in enumerate([2, -2, 3, 0, -3, 1] * 2)]
    m = {"name": "load", "plant": {"num": [2.0], "den": [12.0, 1.0], "delay": 4.0, "noise": 0.1,
                                   "disturbance": {"type": "sine", "amplitude": 3.0, "period": 180.0, "phase": 0.3}},
         "controller": {"kc": 0.5, "ti": 12.0, "sp_steps": steps}, "simulation": {"dt": 1.0, "duration": 2300.0}}
    run, k = simulate_loop(loop_from_mapping(m)), 300
    rec = Recording(run.t[k:] - run.t[k], run.sp[k:], run.op[k:], None, run.pv[k:], source="load")
    d = diagnose(rec)
    assert [f.physics for f in d.findings] == ["disturbance"]
    cfg = d.to_config()
    lo, hi = cfg.valve.op_range
    dist = cfg.plant.disturbance
    assert dist.type == "sine" and dist.period == pytest.approx(180.0, rel=0.02)
    assert dist.amplitude * (hi - lo) / 100.0 == pytest.approx(3.0, rel=0.1)       # back in % flow of the run
    phase = 0.3 + 2.0 * np.pi * k / 180.0                                           # at the recording's start
    assert np.angle(np.exp(1j * (dist.phase - phase))) == pytest.approx(0.0, abs=0.2)
    # On plant data fit_after is cross-validated (each block predicted by a model fitted on the other); the twin
    # is the model fitted on the whole record, so it is compared with that model's own prediction.
    assert abs(replay_fit(d, replay_op(cfg, rec).pv) - replay_fit(d, d.predict(rec.op))) <= 2.0


@functools.cache
def declared_twin(span: tuple[float, float] | None):
    """``(diagnosis, twin config, recording)`` of the level loop's plant data (true S = 3, J = 1.5 % travel) with
    OP written on ``span`` (OP at 0 and 100 % travel) and that span declared; None: OP in % but undeclared."""
    rec, _ = with_sp("stiction, level loop", 300.0)
    lo, hi = span or (0.0, 100.0)
    op = lo + (hi - lo) * rec.op / 100.0
    mapped = Recording(rec.t, rec.sp, op, None, rec.pv, source="declared")
    d = diagnose(mapped, op_range=span)
    return d, d.to_config(), mapped


@pytest.mark.parametrize("span", [(0.0, 100.0), (4.0, 20.0), (0.0, 27648.0)], ids=["%", "mA", "counts"])
def test_a_declared_span_makes_the_twins_travel_the_real_travel(span):
    """Known truth: with OP's span declared, op_range is that span and S, J are the diagnosis' figures in %
    travel (near the truth, 3 and 1.5), whatever OP's units; the open-loop replay fits as the diagnosis did."""
    d, cfg, rec = declared_twin(span)
    travel = d.to_json()["friction"]["travel"]
    assert cfg.valve.op_range == pytest.approx(span)
    found = [cfg.valve.S, cfg.valve.J]
    assert found == pytest.approx([travel["S"]["value"], travel["J"]["value"]], rel=0.1, abs=0.1)
    assert found == pytest.approx([3.0, 1.5], rel=0.3)
    assert replay_fit(d, replay_op(cfg, rec).pv) == pytest.approx(d.explanation.fit_after, abs=2.0)


def test_without_a_declared_span_the_twins_travel_stays_the_unit_free_frame():
    """The same recording with no span: op_range maps OP onto the unit-free frame (not 0..100), S and J are in it,
    and the open-loop replay still fits as the diagnosis did."""
    d, cfg, rec = declared_twin(None)
    assert not d.frame.known
    assert cfg.valve.op_range == pytest.approx((d.frame.op_level(0.0), d.frame.op_level(100.0)))
    assert cfg.valve.op_range != pytest.approx((0.0, 100.0), abs=1.0)
    found = [cfg.valve.S, cfg.valve.J]
    internal = [d.frame.gain * d.friction.parameters[k] for k in ("S", "J")]
    assert found == pytest.approx(internal, rel=0.01)
    assert replay_fit(d, replay_op(cfg, rec).pv) == pytest.approx(d.explanation.fit_after, abs=2.0)


@pytest.mark.slow
def test_the_twins_plant_says_which_nominal_parameter_moved_and_from_what_to_what():
    """A loop whose nominal time constant is 30 % short: the twin's plant is the nominal one with the time
    constant the data moved, and its header says so with both values; the exact nominal is held."""
    from valve_emulator.benchmark.cases import Case, loop_mapping, setpoint_steps

    loop = loop_mapping([2.0], [20.0, 1.0], 2.0, 0.5, 20.0, duration=2300.0, seed=5,
                        sp_steps=setpoint_steps([2, -2] * 12, 100.0))
    short = generate(Case("short tau", {}, loop, {"plant": {"den": [14.0, 1.0]}}, noise=0.02))
    exact = generate(Case("exact", {}, loop, {}, noise=0.02))
    twin = diagnose(short[0], short[1]).twin()
    moved = next(line for line in twin.provenance if line.startswith("plant.num"))
    assert "time constant 1 (s) moved from 14 to" in moved
    den = twin.config.plant.den
    assert den[-2] / den[-1] == pytest.approx(20.0, rel=0.15)     # the time constant of a first-order den
    held = next(line for line in diagnose(exact[0], exact[1]).twin().provenance if line.startswith("plant.num"))
    assert "held as a prior" in held


def test_the_twin_leaves_out_a_valve_model_it_has_no_keys_for(monkeypatch):
    """A new valve model without a twin role is not written as a deadband: the valve keeps the model's S and J,
    and the header says what the twin lacks."""
    monkeypatch.setattr(base, "_REGISTRY", dict(base._REGISTRY))
    register(StrokeRate())
    rec, model = slow_valve()
    d = diagnose(rec, model, candidates=[TOY])
    assert [f.physics for f in d.findings] == [TOY]
    twin = d.twin()
    assert (twin.config.valve.S, twin.config.valve.J) == (model.valve.S, model.valve.J) == (0.0, 0.0)
    assert f"Left out: the {TOY} finding (valve slot) has no keys in the loop config, so the twin lacks it." \
        in twin.provenance
    assert loop_from_mapping(__import__("yaml").safe_load(twin.text())).valve == twin.config.valve
