"""Closed loops of the project's simulator as a plant historian keeps them (t, sp, op, pv): the shared
fixture of the plant-data tests (diagnosis, load check, the command line)."""

from __future__ import annotations

import numpy as np

from valve_emulator.benchmark.cases import loop_mapping, setpoint_steps
from valve_emulator.config import loop_from_mapping
from valve_emulator.recordings.recording import Recording
from valve_emulator.simulation.loop import simulate_loop

STEPS_150 = setpoint_steps([2, -2, 3, 0, -3, 1, 2, -1] * 2, 150.0, start=200.0)
STEPS_300 = setpoint_steps([2, -2, 3, 0, -3, 1, 2, -1] * 2, 300.0, start=200.0)


def simulate(num, den, delay, kc, ti, *, S=0.0, J=0.0, dt=1.0, duration=1300.0, sp_steps=(), disturbance=None,
             noise=0.05, seed=1, cut=200.0, quantum=None, name="synthetic") -> Recording:
    """A closed loop of the project's simulator (:func:`~valve_emulator.benchmark.cases.loop_mapping`), as a
    historian would keep it (t, sp, op, pv): the first ``cut`` s dropped, PV rounded to ``quantum``."""
    run = simulate_loop(loop_from_mapping(loop_mapping(
        num, den, delay, kc, ti, S=S, J=J, dt=dt, duration=duration, sp_steps=sp_steps, disturbance=disturbance,
        noise=noise, seed=seed, name=name)))
    k = int(round(cut / run.dt))
    pv = run.pv[k:]
    if quantum:
        pv = quantum * np.round(pv / quantum)
    return Recording(run.t[k:] - run.t[k], run.sp[k:], run.op[k:], None, pv, source=name)


def flow_limited_loop(limit: float, op_hi: float, sps, T: int = 3200, seed: int = 0):
    """A PI loop (anti-windup by conditional integration, output clamped to 0..op_hi %) on 1/(10s+1) whose flow
    cannot exceed ``limit`` % travel; SP steps (PV units = % flow) some of which ask for more than the limit."""
    rng = np.random.default_rng(seed)
    a, kc, ti = np.exp(-1.0 / 10.0), 0.8, 12.0
    sp = np.repeat(np.asarray(sps, dtype=float), T // len(sps))
    pv, op = np.zeros(sp.size), np.zeros(sp.size)
    x, integ = 40.0, 40.0 / kc
    for k in range(sp.size):
        pv[k] = x + rng.normal(0.0, 0.2)
        e = sp[k] - pv[k]
        u = kc * (e + integ / ti)
        if 0.0 < u < op_hi or (u >= op_hi and e < 0) or (u <= 0.0 and e > 0):
            integ += e
        op[k] = min(max(kc * (e + integ / ti), 0.0), op_hi)
        x = a * x + (1.0 - a) * min(op[k], limit)
    return sp, op, pv
