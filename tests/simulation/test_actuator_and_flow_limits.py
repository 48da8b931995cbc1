"""The loop's actuator lag (before the valve's friction) and flow limits (after the characteristic).

Known truth: the diagnosis' own signal chain (:func:`valve_emulator.diagnosis.fit.chain.run_chain`) with its
``actuator_lag``, ``stiction`` and ``saturation`` candidates is the model a twin is fitted with; the loop a twin
configures must give the same flow for the same OP, sample for sample.
"""

import dataclasses

import numpy as np
import pytest

from valve_emulator.config import LoopConfig, PlantConfig, SimulationConfig, ValveConfig
from valve_emulator.diagnosis.candidates.actuator_lag import ActuatorLag, first_order_lag
from valve_emulator.diagnosis.candidates.base import ChainContext
from valve_emulator.diagnosis.candidates.saturation import Saturation
from valve_emulator.diagnosis.candidates.stiction import Stiction
from valve_emulator.diagnosis.fit.chain import Active, run_chain
from valve_emulator.physics.actuator import actuator_response
from valve_emulator.simulation.loop import LoopBank, simulate_loop

DT = 1.0
_EPS = 1e-6   # how far beyond J the chain's "moving up" start puts the valve


def wandering_op(seed: int, n: int = 600) -> np.ndarray:
    """A controller-like OP: a random walk with swings of several % travel, within 15..85 %."""
    rng = np.random.default_rng(seed)
    return np.clip(50.0 + np.cumsum(rng.normal(scale=1.2, size=n)), 15.0, 85.0)


def open_loop(valve: ValveConfig) -> LoopConfig:
    return LoopConfig("open", valve=valve, plant=PlantConfig((1.0,), (10.0, 1.0)),
                      simulation=SimulationConfig(dt=DT, duration=100.0))


def loop_flow(valve: ValveConfig, op: np.ndarray) -> np.ndarray:
    """The flow of an open loop (no controller) fed ``op``, from its first sample."""
    return LoopBank([open_loop(valve)]).run(op.size, op=op[:, None])["flow"][:, 0]


def chain_flow(op: np.ndarray, *, tau: float, S: float, J: float, limits: tuple[float, float],
               characteristic: tuple[str, float]) -> np.ndarray:
    """The diagnosis chain's flow for ``op``: lag, stiction (its valve started moving up at OP(0)), the nominal
    characteristic, the saturation."""
    ctx = ChainContext(dt=DT, op=op, op_span=float(np.ptp(op)), valve_model="kano", rest_samples=1,
                       characteristic=characteristic)
    active = {"actuator": Active(ActuatorLag(), np.array([tau])),
              "valve": Active(Stiction(), np.array([S, J, 1.0])),
              "limit": Active(Saturation(), np.array(limits))}
    return run_chain(op, active, ctx)[:, 0]


@pytest.mark.parametrize("seed, tau, S, J, limits, characteristic", [
    (0, 6.0, 4.0, 1.5, (0.0, 55.0), ("linear", 50.0)),
    (1, 2.5, 3.0, 3.0, (15.0, 100.0), ("equal_percentage", 30.0)),
    (2, 15.0, 5.0, 0.5, (10.0, 70.0), ("quick_opening", 50.0)),
], ids=["lag before stiction, high limit", "no-offset stiction, low limit", "long lag, both limits"])
def test_the_loop_gives_the_diagnosis_chains_flow_for_the_same_op(seed, tau, S, J, limits, characteristic):
    """The loop with ``actuator_lag`` and ``flow_limits`` is the chain's actuator → valve → characteristic →
    limit, started as the chain's valve moving up at OP(0) (at rest J + ε behind it): the same flow at every
    sample. Without the lag, or with the lag after the valve (the twin's old approximation), it is not."""
    op = wandering_op(seed)
    half = 0.5 * (S - J)
    valve = ValveConfig(model="kano", S=S, J=J, rest_time=0.5, op0=float(op[0]), initial_direction=1,
                        mv0=float(op[0] - J - _EPS - half), stuck0=True, actuator_lag=tau,
                        characteristic=characteristic[0], rangeability=characteristic[1], flow_limits=limits)
    want = chain_flow(op, tau=tau, S=S, J=J, limits=limits, characteristic=characteristic)
    np.testing.assert_allclose(loop_flow(valve, op), want, rtol=0, atol=1e-9)
    assert np.max(np.abs(loop_flow(dataclasses.replace(valve, actuator_lag=0.0), op) - want)) > 1.0
    assert np.any(np.isin(want, [x for x in limits if 0.0 < x < 100.0]))   # the flow meets its limit


def test_the_actuator_is_the_chains_lag_sample_for_sample():
    """The physics' lag (what the loop's compiled step runs) is the actuator candidate's, started at rest at
    OP(0): the same ZOH recursion and the same sample average."""
    op = wandering_op(5, 400)
    for tau in (0.3, 4.0, 40.0):
        np.testing.assert_allclose(actuator_response(op, tau, DT), first_order_lag(op, [tau], DT)[:, 0],
                                   rtol=0, atol=1e-10)
    np.testing.assert_array_equal(actuator_response(op, 0.0, DT), op)


def test_a_flow_limit_stops_the_flow_but_not_the_valve():
    """OP driven to 80 % with the flow limited to 40 %: MV goes to 80, the flow stops at 40; and the loop starts
    in equilibrium at the limited flow."""
    valve = ValveConfig(op0=30.0, flow_limits=(0.0, 40.0))
    bank = LoopBank([open_loop(valve)])
    out = bank.run(50, op=np.full((50, 1), 80.0))
    assert out["mv"][-1, 0] == pytest.approx(80.0)
    assert np.max(out["flow"]) == 40.0
    high = LoopBank([open_loop(dataclasses.replace(valve, op0=60.0))])
    assert high.flow[0] == 40.0 and high.pv[0] == 0.0   # at rest at the limited flow: pv0


def test_an_actuator_lag_delays_the_valve_behind_a_step_in_closed_loop():
    """A set-point step: with an actuator lag the valve follows the controller's OP late (MV behind OP well
    beyond the stiction band), without one MV stays within the band of OP; same loop otherwise."""
    from valve_emulator.config import ControllerConfig

    cfg = dataclasses.replace(open_loop(ValveConfig(S=1.0, J=0.5)),
                              controller=ControllerConfig(1.0, ti=10.0, sp=0.0, sp_steps=((10.0, 5.0),)),
                              simulation=SimulationConfig(dt=DT, duration=60.0))
    lagged = dataclasses.replace(cfg, valve=dataclasses.replace(cfg.valve, actuator_lag=8.0))
    gap = {name: np.max(np.abs(r.op - r.mv)) for name, r in (("none", simulate_loop(cfg)),
                                                           ("lag", simulate_loop(lagged)))}
    assert gap["none"] <= 1.0 + 1e-9
    assert gap["lag"] > 3.0
