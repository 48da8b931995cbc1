"""Closed loops of the project's simulator as a plant historian keeps them (t, sp, op, pv): the shared
fixture of the plant-data tests (diagnosis, load check, the command line)."""

from __future__ import annotations

import numpy as np

from valve_emulator.config import loop_from_mapping
from valve_emulator.recordings.recording import Recording
from valve_emulator.simulation.loop import simulate_loop

STEPS_150 = [(200 + 150 * i, float(v)) for i, v in enumerate([2, -2, 3, 0, -3, 1, 2, -1] * 2)]
STEPS_300 = [(200 + 300 * i, float(v)) for i, v in enumerate([2, -2, 3, 0, -3, 1, 2, -1] * 2)]


def simulate(num, den, delay, kc, ti, *, S=0.0, J=0.0, dt=1.0, duration=1300.0, sp_steps=(), disturbance=None,
             noise=0.05, seed=1, cut=200.0, quantum=None, name="synthetic") -> Recording:
    """A closed loop of the project's simulator, as a historian would keep it (t, sp, op, pv)."""
    plant = {"num": list(num), "den": list(den), "delay": delay, "pv0": 0.0, "noise": noise}
    if disturbance:
        plant["disturbance"] = disturbance
    cfg = loop_from_mapping({
        "name": name, "valve": {"S": S, "J": J}, "plant": plant,
        "controller": {"kc": kc, "ti": ti, "sp": 0.0, "bias": 50.0,
                       "sp_steps": [list(s) for s in sp_steps] or [[10.0, 1.0]]},
        "simulation": {"dt": dt, "duration": duration, "seed": seed}})
    run = simulate_loop(cfg)
    k = int(round(cut / run.dt))
    pv = run.pv[k:]
    if quantum:
        pv = quantum * np.round(pv / quantum)
    return Recording(run.t[k:] - run.t[k], run.sp[k:], run.op[k:], None, pv, source=name)
