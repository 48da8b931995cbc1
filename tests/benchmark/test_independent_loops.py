"""The independent loop simulator is right on its own terms: plants, valve friction, controller timing, onset."""

from __future__ import annotations

import ast
import inspect
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from valve_emulator.benchmark import independent
from valve_emulator.benchmark.independent import (
    FAMILIES,
    Controller,
    DataDrivenFriction,
    KarnoppFriction,
    Loop,
    Measurement,
    Plant,
    Valve,
    draw,
    loop_margins,
    simulate,
)
from valve_emulator.config import loop_from_mapping


def _step_response(plant: Plant, *, dt: float = 0.5, duration: float = 60.0, step_at: int = 4,
                   size: float = 10.0, valve: Valve | None = None) -> tuple[np.ndarray, np.ndarray]:
    n = int(round(duration / dt)) + 1
    op = np.where(np.arange(n) >= step_at, 50.0 + size, 50.0)
    rec, _ = simulate(Loop(plant=plant, valve=valve or Valve(), dt=dt, duration=duration, manual_op=tuple(op)))
    return rec.t - step_at * dt, rec.pv - plant.pv0


def test_a_first_order_plant_reaches_63_percent_at_its_time_constant():
    t, y = _step_response(Plant("fopdt", gain=2.0, tau=10.0))
    at_tau = y[np.flatnonzero(np.isclose(t, 10.0))[0]]
    assert at_tau / (2.0 * 10.0) == pytest.approx(1 - math.exp(-1), abs=0.005)
    assert y[t <= 0] == pytest.approx(0.0)


def test_a_dead_time_between_samples_delays_the_response_by_exactly_that_time():
    t, y = _step_response(Plant("fopdt", gain=1.0, tau=5.0, delay=1.75), dt=0.5)
    assert np.all(np.abs(y[t <= 1.5]) < 1e-9)                    # nothing before θ = 1.75 s
    expected = 10.0 * (1 - np.exp(-(t - 1.75) / 5.0))
    late = t >= 2.0
    assert np.max(np.abs(y[late] - expected[late])) < 0.01 * 10.0


def test_a_second_order_plant_follows_its_analytic_step_response():
    t1, t2 = 3.0, 8.0
    t, y = _step_response(Plant("sopdt", gain=1.5, tau=t2, lag=t1))
    after = t >= 0
    exact = 15.0 * (1 - (t1 * np.exp(-t[after] / t1) - t2 * np.exp(-t[after] / t2)) / (t1 - t2))
    assert np.max(np.abs(y[after] - exact)) < 1e-3 * 15.0


def test_an_integrating_plant_rises_at_its_gain_times_the_flow_change():
    t, y = _step_response(Plant("integrating", gain=0.05), size=10.0)
    slope = np.diff(y[t >= 1.0]) / np.diff(t[t >= 1.0])
    assert slope == pytest.approx(0.05 * 10.0, rel=1e-9)
    t, y = _step_response(Plant("integrating_lag", gain=0.05, lag=4.0), size=10.0)
    assert np.diff(y[-3:]) / 0.5 == pytest.approx(0.05 * 10.0, rel=1e-4)   # the lag's transient has died out


def test_an_equal_percentage_valve_sets_the_flow_change_through_its_characteristic():
    valve = Valve(characteristic="equal_percentage", rangeability=50.0)
    t, y = _step_response(Plant("integrating", gain=0.05), size=10.0, valve=valve)
    flow = lambda x: 100.0 * 50.0 ** (x / 100.0 - 1.0)  # noqa: E731
    assert np.diff(y[-3:]) / 0.5 == pytest.approx(0.05 * (flow(60.0) - flow(50.0)), rel=1e-9)


def _ramp(points: list[float], step: float = 0.01) -> np.ndarray:
    legs = [np.arange(a, b, step if b > a else -step) for a, b in zip(points[:-1], points[1:])]
    return np.concatenate(legs + [[points[-1]]])


def _run(friction, u: np.ndarray, h: float = 0.1) -> np.ndarray:
    return np.array([friction(x, k * h, h) for k, x in enumerate(u)])


@pytest.mark.parametrize("order", ["lag_first", "friction_first"])
def test_an_actuator_lag_moves_the_stem_as_a_first_order_lag_of_op(order):
    """Known truth: OP steps 50 → 60 at sample 10 and is held; a healthy stem behind a 5-s lag, in either order,
    is at 50 + 10·(1 − e^(−s/5)) once the new OP has been applied for s seconds. The recorded travel is the stem's
    at the end of each sample's first substep (h = dt / substeps); the plant's PV follows the travel."""
    dt, tau = 1.0, 5.0
    loop = Loop(plant=Plant("fopdt", gain=1.0, tau=3.0), valve=Valve(actuator_lag=tau, order=order), dt=dt,
                duration=60.0, manual_op=tuple(np.where(np.arange(61) >= 10, 60.0, 50.0)))
    rec, truth = simulate(loop, record_mv=True)
    h = dt / loop.substeps
    applied = np.arange(61) * dt - 10 * dt + h
    want = np.where(applied > 0, 50.0 + 10.0 * (1.0 - np.exp(-applied / tau)), 50.0)
    assert rec.mv == pytest.approx(want, abs=1e-9)
    assert np.array_equal(rec.mv, truth["mv"])
    assert rec.pv[9] == pytest.approx(loop.plant.pv0) and rec.pv[-1] - loop.plant.pv0 == pytest.approx(10.0, abs=0.05)


def test_without_friction_the_valve_tracks_its_input_exactly():
    u = 50.0 + np.cumsum(np.random.default_rng(0).normal(0, 0.3, 2000))
    assert np.array_equal(_run(DataDrivenFriction(0.0, 0.0, u[0], rest_time=0.15, onset=0.0), u), np.clip(u, 0, 100))
    rec, truth = simulate(Loop(plant=Plant("fopdt", gain=1.0, tau=5.0), controller=Controller(kc=1.0, ti=5.0),
                               measurement=Measurement(noise=0.2), duration=200.0), record_mv=True)
    assert np.array_equal(rec.mv, rec.op)


def test_a_sticky_valve_sticks_until_its_input_has_moved_S_and_then_jumps_by_J():
    """On a ramp 50 → 60 → 45 from rest after a downward motion, the 2005 definition: after each reversal the
    output holds until the input has moved S, then jumps by J, then moves with the input at (S − J)/2 from it."""
    S, J, step = 4.0, 1.5, 0.01
    u = _ramp([50.0, 60.0, 45.0], step)
    mv = _run(DataDrivenFriction(S, J, 50.0, rest_time=0.15, onset=0.0, direction=-1), u)
    for start, sign in ((0, 1.0), (int(np.argmax(u)), -1.0)):
        moved = sign * (u[start:] - u[start])
        first = start + int(np.flatnonzero(mv[start:] != mv[start])[0])
        assert moved[first - start] == pytest.approx(S, abs=1.5 * step)      # stuck until S
        assert np.all(mv[start:first] == mv[start])
        assert sign * (mv[first] - mv[first - 1]) == pytest.approx(J, abs=1.5 * step)   # the slip jump
        assert mv[first + 100] == pytest.approx(u[first + 100] - sign * (S - J) / 2.0)  # then moves, offset
    assert abs(mv[-1] - 45.0) == pytest.approx((S - J) / 2.0)                # undershoot: never reaches OP


def test_a_valve_that_stops_needs_only_J_to_move_on_the_same_way():
    S, J = 4.0, 1.5
    u = np.concatenate([_ramp([50.0, 55.0]), np.full(50, 55.0), _ramp([55.0, 58.0])])
    mv = _run(DataDrivenFriction(S, J, 50.0, rest_time=0.15, onset=0.0, direction=1), u)
    rest = int(np.flatnonzero(u == 55.0)[-1])
    first = rest + int(np.flatnonzero(mv[rest:] != mv[rest])[0])
    assert u[first] - 55.0 == pytest.approx(J, abs=0.015)


def test_the_karnopp_valve_reverses_after_S_and_slips_by_J():
    S, J, h = 4.0, 1.5, 0.05
    u = np.concatenate([_ramp([50.0, 60.0, 45.0], 0.01), np.full(400, 45.0)])
    mv = _run(KarnoppFriction(S, J, 50.0, period=0.5, onset=0.0, direction=-1), u, h)
    top = int(np.argmax(u))
    held = mv[top + 50]                                 # stuck soon after the reversal
    first = top + 50 + int(np.flatnonzero(np.abs(mv[top + 50:] - held) > 1e-6)[0])
    assert u[top] - u[first] == pytest.approx(S, abs=0.05)
    later = first + 30                                  # 1.5 s later: slipped and moving with the input
    assert mv[later] == pytest.approx(u[later] + (S - J) / 2.0, abs=0.05)
    assert held - (mv[later] - (u[later] - u[first])) == pytest.approx(J, abs=0.05)   # the slip jump
    assert mv[-1] == pytest.approx(45.0 + (S - J) / 2.0, abs=0.01)          # at rest at u + fc


def test_the_controller_acts_on_the_pv_of_the_sample_before():
    c = Controller(kc=0.8, ti=12.0, sp_steps=((20.0, 51.0),))
    rec, _ = simulate(Loop(plant=Plant("fopdt", gain=1.0, tau=8.0, delay=1.3), controller=c,
                           measurement=Measurement(noise=0.3), duration=150.0))
    e = rec.sp[1:] - rec.pv[:-1]                    # e(k) = sp(k) − pv(k−1)
    expected = 50.0 + c.kc * (e + np.cumsum(e) / c.ti)
    assert np.max(np.abs(rec.op[1:] - expected)) < 1e-9
    e_now = rec.sp[1:] - rec.pv[1:]
    assert np.max(np.abs(rec.op[1:] - (50.0 + c.kc * (e_now + np.cumsum(e_now) / c.ti)))) > 0.1


def test_a_direct_acting_controller_closes_a_loop_whose_gain_is_negative():
    plant = Plant("integrating", gain=-0.05, delay=1.0)
    rec, _ = simulate(Loop(plant=plant, controller=Controller(kc=4.0, ti=40.0, action="direct",
                                                              sp_steps=((10.0, 52.0),)), duration=600.0))
    assert rec.pv[-50:] == pytest.approx(52.0, abs=0.05)


def test_the_integral_does_not_wind_up_while_op_is_at_its_limit():
    plant = Plant("fopdt", gain=0.1, tau=5.0)      # SP 60 asks for OP 150: OP pins at 100
    rec, _ = simulate(Loop(plant=plant, controller=Controller(kc=2.0, ti=5.0, sp_steps=((5.0, 60.0), (200.0, 50.0))),
                           duration=260.0))
    assert np.all(rec.op[(rec.t > 50) & (rec.t < 200)] == 100.0)
    assert np.all(rec.op[rec.t >= 210] < 100.0)        # leaves the limit at once when SP comes back


def test_a_valve_is_healthy_until_the_onset_of_its_friction():
    valve = Valve(friction="data_driven", S=3.0, J=1.0, order="friction_first", onset=300.0)
    rec, _ = simulate(Loop(plant=Plant("fopdt", gain=1.0, tau=10.0, delay=2.0), valve=valve,
                           controller=Controller(kc=1.0, ti=10.0), measurement=Measurement(noise=0.1),
                           duration=600.0), record_mv=True)
    before, after = rec.t < 300.0, rec.t > 300.0
    assert np.array_equal(rec.mv[before], rec.op[before])
    moved_op = np.abs(np.diff(rec.op[after])) > 0.05
    held = np.diff(rec.mv[after]) == 0.0
    assert np.mean(held[moved_op]) > 0.5                 # after it, the valve mostly holds while OP moves


def test_pv_is_quantised_to_the_converter_step():
    rec, _ = simulate(Loop(plant=Plant("fopdt", gain=1.0, tau=5.0), controller=Controller(kc=1.0, ti=5.0,
                      sp_steps=((5.0, 52.0),)), measurement=Measurement(noise=0.1, quantum=0.25), duration=100.0))
    assert np.allclose(rec.pv / 0.25, np.round(rec.pv / 0.25), atol=1e-9)
    assert len(np.unique(rec.pv)) > 3


def test_loop_margins_match_the_closed_form_of_a_delayed_integrator():
    """L = Kc·e^{−θs}/s: crossover at ω = Kc, PM = 90° − Kc·θ; phase crossover at π/(2θ), GM = π/(2 θ Kc)."""
    kc, theta = 0.2, 2.0
    m = loop_margins(Plant("integrating", gain=1.0, delay=theta - 0.5), kc, 1e12, 0.5)
    assert m["PM"] == pytest.approx(90.0 - math.degrees(kc * theta), abs=0.05)
    assert m["GM"] == pytest.approx(math.pi / (2 * theta * kc), rel=1e-3)
    assert m["Ms"] > 1.0


@pytest.mark.parametrize("family", list(FAMILIES))
def test_every_family_draws_a_well_formed_recording_and_a_nominal_model_the_loader_accepts(family):
    rec, truth, nominal = draw(family, np.random.default_rng(7))
    n = len(rec)
    assert n > 1000 and all(np.all(np.isfinite(x)) for x in (rec.t, rec.sp, rec.op, rec.pv))
    assert np.allclose(np.diff(rec.t), truth["dt"]) and np.all((rec.op >= 0) & (rec.op <= 100))
    assert np.std(rec.pv) > 0 and np.std(rec.op) > 0
    assert truth["expected"] == ("stiction" if truth["S"] >= independent.MATERIAL_S else "no_stiction")
    cfg = loop_from_mapping(nominal)
    assert cfg.valve.S == 0 and cfg.plant.delay == truth["plant"]["delay"]
    if family == "late_onset":
        assert 0.2 * rec.t[-1] <= truth["onset"] <= 0.8 * rec.t[-1]
    if family == "aggressive_pi":
        assert 1.2 <= truth["margins"]["GM"] <= 1.6


def test_the_simulator_shares_no_code_with_the_searched_model():
    tree = ast.parse(inspect.getsource(independent))
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)} | {
        a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    package = {m for m in imported if m and m.startswith("valve_emulator")}
    assert package == {"valve_emulator.recordings"}


def _document(answer, S=None, J=None, interval=0.1, codes=(), physics=()):
    value = lambda x: {"value": x, "interval": [x * (1 - interval), x * (1 + interval)], "units": "% travel"}  # noqa: E731
    friction = None if S is None else {
        "physics": "stiction" if J else "deadband", "S": value(S), "J": value(J),
        "travel": {"S": value(S), "J": value(J)}, "band": {"S": {"value": S / 10.0}, "J": {"value": J / 10.0}}}
    return {"answer": answer, "friction": friction, "reasons": [{"code": c, "sentence": ""} for c in codes],
            "findings": [{"physics": p} for p in physics]}


def test_the_benchmark_scores_answers_intervals_edges_and_disagreements_against_the_truth():
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    from bench_unseen_loops import score

    sticky = {"expected": "stiction", "tuning": False, "S": 4.0, "J": 2.0}
    row = score(_document("stiction", 4.2, 1.9, codes=["stiction"], physics=["stiction"]), sticky)
    assert row["correct"] and row["S_cov"] and row["J_cov"] and not row["disagree"]
    assert row["S_err"] == pytest.approx(0.05) and row["J_err"] == pytest.approx(0.05)
    row = score(_document("stiction", 5.0, 1.0, interval=0.05, physics=["stiction"]), sticky)
    assert not row["S_cov"] and not row["J_cov"]
    healthy = {"expected": "no_stiction", "tuning": False, "S": 0.0, "J": 0.0}
    row = score(_document("no_stiction", physics=["stiction"]), healthy)
    assert row["correct"] and row["disagree"]
    tuned = {**healthy, "tuning": True}
    assert not score(_document("no_stiction", codes=["linear"]), tuned)["correct"]
    assert score(_document("no_stiction", codes=["tuning"]), tuned)["correct"]
    assert not score(_document("cannot_tell"), healthy)["correct"]
    assert not any(score(_document("cannot_tell"), truth)["wrong"] for truth in (healthy, sticky))
    assert score(_document("stiction", 1.0, 0.5), healthy)["wrong"]
    assert score(_document("no_stiction"), sticky)["wrong"] and not score(_document("no_stiction"), healthy)["wrong"]
    assert not score(_document("no_stiction", codes=["linear"]), tuned)["wrong"]   # not right (no tuning), not wrong


def test_the_benchmark_counts_a_parameter_on_a_search_edge_reported_as_a_value():
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    from types import SimpleNamespace

    from bench_unseen_loops import edges

    from valve_emulator.diagnosis.candidates.characteristic import R_MAX
    from valve_emulator.diagnosis.explain.result import Finding

    def curve(R, interval):
        return Finding(physics="characteristic", parameters={"kind": "equal_percentage", "R": R}, windows=(),
                       evidence="", description="", intervals={"R": interval})

    recording = SimpleNamespace(dt=1.0, op=np.linspace(20.0, 60.0, 500))
    as_value, as_bound, inside = curve(R_MAX, (300.0, R_MAX)), curve(R_MAX, (R_MAX, np.inf)), curve(30.0, (20.0, 50.0))
    doc = lambda *found: SimpleNamespace(findings=found, recording=recording,  # noqa: E731
                                         explanation=SimpleNamespace(plant={"taus": [12.0]}))
    assert edges(doc(as_value, inside)) == (1, 2)
    assert edges(doc(as_bound, inside)) == (0, 2)
    assert edges(doc()) == (0, 0)
    linear = Finding(physics="characteristic", parameters={"kind": "linear", "R": None}, windows=(), evidence="",
                     description="", intervals={})
    assert edges(doc(linear)) == (0, 1)   # a parameter without a value is no value on an edge


def test_the_benchmark_table_counts_right_and_wrong_calls_apart_from_hedges():
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    from bench_unseen_loops import HEADER, score, summary

    sticky = {"expected": "stiction", "tuning": False, "S": 4.0, "J": 2.0}
    healthy = {"expected": "no_stiction", "tuning": False, "S": 0.0, "J": 0.0}
    rows = [{"family": "flow_sticky", "mode": "model", "seconds": 1.0, "edge": 0, "found": 1, **score(doc, truth)}
            for doc, truth in [(_document("stiction", 4.1, 2.0, physics=["stiction"]), sticky),
                               (_document("no_stiction"), sticky), (_document("cannot_tell"), sticky),
                               (_document("stiction", 2.0, 1.0, physics=["stiction"]), healthy)]]
    table = [dict(zip(HEADER, r)) for r in summary(rows)]
    assert [t["family"] for t in table] == ["flow_sticky", "all"]
    assert table[0]["correct"] == "1/4" and table[0]["wrong"] == "2/4"
    assert table[0]["answers"] == "cannot_tell:1 no_stiction:1 stiction:2"
