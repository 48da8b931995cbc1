"""Drive a loop config with a recording: its OP (open loop) or its set point (closed loop).

``valve-emulator simulate TWIN.yaml --replay REC`` compares a loop — typically the twin a diagnosis wrote —
with the recording it came from:

* **open loop** (:func:`replay_op`): the recorded OP, mapped to % travel by ``valve.op_range``, drives valve
  and plant, as the diagnosis' free-run fit does. The controller is cut out (its ``op_limits`` still clip the
  OP: an OP the controller could not have written is not replayed) and the measurement noise is left out, so
  the PV is the loop's prediction, comparable with the recorded PV sample for sample.
* **closed loop** (:func:`replay_sp`): the recorded SP drives the loop's own controller (in auto), which
  writes OP; noise stays in, because inside a loop it changes what the loop does (when a sticky valve slips).
  The result is compared by its character — a limit cycle's period and amplitude — not sample for sample.

A recording starts mid-cycle, and a sticky valve put at rest at the first OP may never slip on an OP that
swings little more than S. So the open-loop replay starts as the diagnosis' default valve start does
(:mod:`valve_emulator.diagnosis.candidates.valve_start`): the loop first runs through the record's first fifth
(at least 100 samples) mirrored in time, ``OP[K], …, OP[1]``, which joins the record at ``OP[0]``; by then the
valve is in a state a valve cycling on this OP reaches; the plant then starts at rest, as the fit's does.
(An actuator lag, ``valve.actuator_lag``, runs through the pre-roll with the valve; the fit's chain instead lags
the record from rest at OP(0) and pre-rolls the valve on the lagged OP, which a twin's carried start reproduces.)
A loop that carries the state its recording starts in (a twin's ``valve.mv0``, ``valve.stuck0``,
``valve.initial_direction`` and ``plant.rest_flow``, the state the diagnosis' fit started in) starts there
instead, with no pre-roll, and so matches the recording from its first sample.
The closed-loop replay starts the same way and follows the recorded OP over that same first fifth (the loop
is then where the recording is, mid-cycle), then hands the valve to the controller, which continues bumplessly
from there: a loop started at rest with PV at SP could sit on a stuck valve for a long time before its first
slip. Both run on the recording's time grid, which must be uniform with the config's ``simulation.dt`` as its
step.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from valve_emulator.config import DisturbanceConfig, LoopConfig
from valve_emulator.recordings.recording import Recording, RecordingError
from valve_emulator.simulation.loop import LoopBank

__all__ = ["carries_start", "op_travel", "pre_roll_length", "pre_rolled", "replay_op", "replay_sp"]

_EPS = 1e-6   # % travel: a valve put at rest J + this below OP slips at the first sample that rises


def op_travel(config: LoopConfig, op: np.ndarray) -> np.ndarray:
    """A recording's OP (in its own units) as % travel, by ``valve.op_range`` (OP at 0 and 100 %)."""
    lo, hi = config.valve.op_range
    return 100.0 * (np.asarray(op, dtype=float) - lo) / (hi - lo)


def _check_grid(config: LoopConfig, rec: Recording) -> None:
    src = rec.source or "recording"
    if len(rec) < 2:
        raise RecordingError(f"{src}: a replay needs at least 2 samples, got {len(rec)}")
    dt = config.simulation.dt
    steps = np.diff(rec.t)
    bad = np.flatnonzero(np.abs(steps - dt) > 0.01 * dt)
    if bad.size:
        i = int(bad[0])
        raise RecordingError(f"{src}: line {i + 3}: sample step {steps[i]:g} s differs from the loop's "
                             f"simulation.dt = {dt:g} s by more than 1 %; replay a recording sampled every dt")


def _recording(config: LoopConfig, rec: Recording, out: dict[str, np.ndarray], *, sp=None) -> Recording:
    """The run as a recording on ``rec``'s grid (time from 0); ``sp`` replaces the run's set point."""
    sp = out["sp"][:, 0] if sp is None else sp
    return Recording(t=np.asarray(rec.t) - rec.t[0], sp=sp, op=out["op"][:, 0], mv=out["mv"][:, 0],
                     pv=out["pv"][:, 0], extra={"flow": out["flow"][:, 0], "stuck": out["stuck"][:, 0].astype(float)},
                     source=config.source or config.name)


def pre_roll_length(T: int) -> int:
    """Samples of the mirrored pre-roll of a record of ``T`` samples: its first fifth, at least 100."""
    return min(T - 1, max(100, T // 5))


def carries_start(config: LoopConfig) -> bool:
    """True when ``config`` carries the state its recording starts in (``valve.mv0``, a twin's): a replay then
    starts there instead of after the mirrored pre-roll."""
    return config.valve.mv0 is not None


def _lead_in(config: LoopConfig, op: np.ndarray) -> LoopBank:
    """A bank of ``config`` at the recording's first sample, the valve following the external OP: in the state
    the config carries (:func:`carries_start`), else after the mirrored pre-roll of ``op`` (% travel) with the
    plant at rest for the flow that left it."""
    if carries_start(config):
        bank = LoopBank([config])
        bank.follow_external(True)
        return bank
    return pre_rolled(config, op)


def pre_rolled(config: LoopConfig, op: np.ndarray) -> LoopBank:
    """A bank of ``config`` whose valve has run through the mirrored pre-roll of ``op`` (% travel) and whose
    plant is at rest for the flow that left it; the valve follows the external OP. Its ``mv``, ``stuck`` and
    ``direction`` are the valve's state at the recording's first sample."""
    K = pre_roll_length(op.size)
    rolled = op[K:0:-1]
    start = float(np.clip(rolled[0] - config.valve.J - _EPS, 0.0, 100.0))   # about to move up at OP[K]
    valve = dataclasses.replace(config.valve, op0=start, initial_direction=1, mv0=None, stuck0=True)
    controller = config.controller and dataclasses.replace(config.controller, bias=start, sp_steps=())
    plant = dataclasses.replace(config.plant, disturbance=_delayed(config.plant.disturbance, K * config.simulation.dt))
    bank = LoopBank([dataclasses.replace(config, valve=valve, plant=plant, controller=controller)])
    bank.follow_external(True)
    bank.run(K, op=rolled[:, None])
    bank.settle_plants()   # the pre-roll is for the valve: the plant starts at rest, as the fit's does
    return bank


def _delayed(d: DisturbanceConfig, lead: float) -> DisturbanceConfig:
    """The load disturbance as seen from a run that starts ``lead`` seconds before the recording: its time 0 stays
    the recording's first sample."""
    if d.type == "sine":
        return dataclasses.replace(d, phase=d.phase - 2.0 * np.pi * lead / d.period)
    if d.type == "step":
        return dataclasses.replace(d, time=d.time + lead)
    return d


def _operating_point_fixed(config: LoopConfig) -> LoopConfig:
    """``config`` with ``plant.u0`` given: unset, it is the initial flow of the loop as configured, which a
    replay (that starts the valve elsewhere) must keep."""
    if config.plant.u0 is not None:
        return config
    return dataclasses.replace(config, plant=dataclasses.replace(config.plant, u0=float(LoopBank([config]).flow[0])))


def _op(config: LoopConfig, rec: Recording) -> np.ndarray:
    """The recorded OP in % travel, within what the controller could write and the valve's travel."""
    lo, hi = config.controller.op_limits if config.controller is not None else (0.0, 100.0)
    return np.clip(op_travel(config, rec.op), max(lo, 0.0), min(hi, 100.0))


def replay_op(config: LoopConfig, rec: Recording) -> Recording:
    """The loop's PV for the recorded OP, open loop and noise-free (see the module docstring).

    Returns a recording on ``rec``'s grid (time from 0) with ``op`` and ``mv`` in % travel and the recorded set
    point (NaN where there is none: no controller ran).
    """
    _check_grid(config, rec)
    op = _op(config, rec)
    config = _operating_point_fixed(config)
    cfg = dataclasses.replace(config, plant=dataclasses.replace(config.plant, noise=0.0), controller=None)
    return _recording(cfg, rec, _lead_in(cfg, op).run(op.size, op=op[:, None]), sp=rec.sp)


def replay_sp(config: LoopConfig, rec: Recording) -> Recording:
    """The loop in closed loop with its own controller, driven by the recorded SP (see the module docstring).

    Raises
    ------
    RecordingError
        The recording has no set point (naming it).
    ValueError
        The loop has no controller.
    """
    src = rec.source or "recording"
    sp = np.asarray(rec.sp, dtype=float)
    if not np.all(np.isfinite(sp)):
        raise RecordingError(f"{src}: no set point (the sp column is missing or has gaps); a closed-loop replay "
                             "drives the loop with the recorded SP")
    if config.controller is None:
        raise ValueError(f"{config.source or config.name}: the loop has no controller to replay the set point with")
    _check_grid(config, rec)
    op = _op(config, rec)
    config = _operating_point_fixed(config)
    cfg = dataclasses.replace(config, controller=dataclasses.replace(config.controller, mode="auto"))
    bank = _lead_in(cfg, op)
    K = pre_roll_length(op.size)
    head = bank.run(K, sp=sp[:K, None], op=op[:K, None])
    bank.follow_external(False)
    tail = bank.run(op.size - K, sp=sp[K:, None])
    return _recording(cfg, rec, {k: np.concatenate([head[k], tail[k]]) for k in head})
