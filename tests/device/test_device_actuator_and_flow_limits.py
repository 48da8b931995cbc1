"""A served loop runs the actuator lag and the flow limits as the offline loop does (one physics)."""

import numpy as np
import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.simulation.loop import simulate_loop
from valve_emulator.testing import Emulator

LOOP = {"unit": 1, "valve": {"model": "kano", "S": 3.0, "J": 1.0, "actuator_lag": 4.0, "flow_limits": [0, 52]},
        "plant": {"num": [2.0], "den": [8.0, 1.0], "delay": 2.0, "pv_range": [-50.0, 50.0]},
        "controller": {"kc": 1.5, "ti": 6.0, "sp": 0.0, "bias": 50.0, "sp_steps": [[5.0, 4.0], [60.0, -3.0]]},
        "simulation": {"dt": 0.5}}


@pytest.mark.parametrize("seconds", [30.0, 90.0])
def test_the_device_and_the_offline_loop_agree_with_an_actuator_and_flow_limits(seconds):
    """The emulated device (manual clock) and ``simulate_loop`` of the same loop show the same OP, MV, flow and
    PV at the same sample; the loop limit-cycles through the lag and its flow meets the limit (so both elements
    are exercised)."""
    config = server_from_mapping({"device": {"tick": 0.5}, "loops": [LOOP]})
    loop = config.loops[0]
    offline = simulate_loop(loop, duration=seconds)
    with Emulator(config, clock="manual") as emu:
        emu.advance(seconds)
        k = int(round(emu.time / emu.dt))
        state = emu.state()
    assert state["op_f32"] == pytest.approx(offline.op[k], abs=1e-4)
    assert state["mv_f32"] == pytest.approx(offline.mv[k], abs=1e-4)
    assert state["pv_f32"] == pytest.approx(offline.pv[k], abs=1e-4)
    assert state["flow_pct"] == pytest.approx(offline.extra["flow"][k], abs=0.006)
    assert np.max(offline.extra["flow"][: k + 1]) == 52.0
    assert np.max(np.abs(offline.op[: k + 1] - offline.mv[: k + 1])) > 3.0   # beyond the band: the lag
