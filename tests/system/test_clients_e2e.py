"""End to end in accelerated time: the emulator (no internal controller) + the soft PLC + the recorder on the
undershoot concentration loop of Choudhury, Thornhill & Shah (2005) reproduce the offline limit cycle, and the
recording shows the valve stuck after every reversal until OP has moved S."""

from __future__ import annotations

import asyncio
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from valve_emulator.clients._channels import emulator_channels
from valve_emulator.clients.pi_controller import ControllerSettings, run_controller
from valve_emulator.clients.recorder import RecorderOptions, record
from valve_emulator.config import ServerConfig, load_loop
from valve_emulator.device.server import EmulatorServer
from valve_emulator.physics.controller import PID
from valve_emulator.recordings.recording import read_csv
from valve_emulator.simulation.limit_cycle import measure_limit_cycle
from valve_emulator.simulation.loop import simulate_loop

pytestmark = pytest.mark.usefixtures("no_task_leak")

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "table1" / "concentration_undershoot.yaml"
SCALE, DURATION, STEP = 40.0, 640.0, 1.0


def reversals(x: np.ndarray, min_swing: float) -> list[int]:
    """Indices where ``x`` turns around after a swing of at least ``min_swing`` (a zigzag filter; of equal
    samples at a turn, the first counts)."""
    ext, direction, out = 0, 0, []
    for i in range(1, len(x)):
        if direction == 0:
            if x[i] != x[0]:
                direction, ext = (1 if x[i] > x[0] else -1), i
        elif (x[i] - x[ext]) * direction > 0:
            ext = i
        elif (x[ext] - x[i]) * direction >= min_swing:
            out.append(ext)
            direction, ext = -direction, i
    return out


async def test_pi_controller_and_recorder_reproduce_the_offline_limit_cycle(tmp_path):
    cfg = load_loop(CONFIG)
    S = cfg.valve.S
    ctl = cfg.controller
    offline = simulate_loop(cfg, DURATION)
    external = ServerConfig(device=replace(cfg.device, unit=None), loops=(replace(cfg, controller=None),))
    out = tmp_path / "loop.csv"
    # Emulator, PLC and recorder share this event loop: load the PID's compiled kernel now, so that its
    # first use inside the PLC does not stall the loop (and leave a gap in the recording).
    PID(kc=1.0, ti=1.0, dt=1.0)(0.0, 0.0)
    async with EmulatorServer(external, time_scale=SCALE) as srv:
        stop = asyncio.Event()
        # The PLC paces itself on the emulator's clock (one scan per 0.2 simulated s); set point 1 as the
        # config's step to 1.0 (the internal controller's sp_steps).
        plc = asyncio.create_task(run_controller(ControllerSettings(
            port=srv.port, kc=ctl.kc, ti=ctl.ti, bias=ctl.bias, sp=1.0, scan=0.2 / SCALE, time_scale=SCALE,
            device_time="time"), stop=stop))
        summary = await record(RecorderOptions(out=out, channels=emulator_channels(), port=srv.port,
                                               period=STEP / SCALE, step=STEP, until=DURATION))
        stop.set()
        plc_summary = await plc
    # the PLC scanned throughout (a loaded 2-core machine can make it miss some scans at this time-scale)
    assert plc_summary.scans > 0.75 * DURATION / 0.2 and plc_summary.errors == 0

    rec = read_csv(out)                                   # accepted as is, default gap check
    assert rec.columns[:5] == ("t", "sp", "op", "mv", "pv") and {"flow", "stuck", "S", "J"} <= set(rec.extra)
    assert np.all(np.isnan(rec.sp))                       # no internal controller: no set point served
    steps = np.diff(rec.t)
    assert np.mean(np.abs(steps - STEP) < 1e-6) > 0.75    # mostly on the device's time grid (uniform sampling)
    assert summary.rows == len(rec) and rec.t[-1] >= DURATION

    lc = measure_limit_cycle(rec.t, rec.op, last_fraction=0.7)
    ref = measure_limit_cycle(offline.t, offline.op, last_fraction=0.7)
    assert lc.sustained and ref.sustained
    assert abs(lc.period - ref.period) / ref.period < 0.05, (lc.period, ref.period)
    assert abs(lc.amplitude - ref.amplitude) / ref.amplitude < 0.15

    # After every reversal of OP (in the settled cycle) MV does not move until OP has gone S back.
    late = np.flatnonzero(rec.t > 150.0)
    op, mv = rec.op[late], rec.mv[late]
    turns = reversals(op, min_swing=1.0)
    assert len(turns) >= 6, turns
    for r in turns:
        j = r + 1
        while j < len(op) and abs(op[j] - op[r]) < S - 0.2:
            j += 1
        stuck = mv[r + 1:j]
        assert len(stuck) >= 20 and np.ptp(stuck) == 0.0, (rec.t[late][r], stuck)
        if j + 5 < len(op):                               # and once OP has moved S, the valve slips
            assert np.any(mv[j:j + 5] != stuck[0]), rec.t[late][r]
