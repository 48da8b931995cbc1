"""Replaying a recording through a loop (``simulation/replay.py``) and the bank inputs it uses.

Known truth: a loop replayed on its own noise-free run gives that run back — open loop on its OP (a linear
valve has no hidden state), closed loop on its SP (the controller takes over bumplessly).
"""

import dataclasses

import numpy as np
import pytest

from valve_emulator.config import loop_from_mapping
from valve_emulator.recordings.recording import Recording, RecordingError
from valve_emulator.simulation.loop import LoopBank, simulate_loop
from valve_emulator.simulation.replay import op_travel, replay_op, replay_sp

LOOP = {"name": "flow", "valve": {"S": 0.0, "J": 0.0},
        "plant": {"num": [2.0], "den": [12.0, 7.0, 1.0], "delay": 3.5, "pv0": 4.0},
        "controller": {"kc": 0.6, "ti": 9.0, "sp": 4.0, "sp_steps": [[20.0, 6.0], [150.0, 2.5], [260.0, 5.0]]},
        "simulation": {"dt": 0.5, "duration": 400.0}}


@pytest.fixture(scope="module")
def run():
    cfg = loop_from_mapping(LOOP)
    return cfg, simulate_loop(cfg)


def test_run_with_an_op_sequence_equals_writing_it_sample_by_sample():
    cfg = dataclasses.replace(loop_from_mapping(LOOP), controller=None)
    op = 50.0 + 10.0 * np.sin(np.arange(300) / 17.0)
    a, b = LoopBank([cfg]), LoopBank([cfg])
    out = a.run(op.size, op=op[:, None])
    pv = []
    for x in op:
        b.op_external[:] = x
        b.step()
        pv.append(b.pv[0])
    np.testing.assert_array_equal(out["pv"][:, 0], pv)
    assert a.op_external[0] == op[-1]


def test_the_open_loop_replay_of_a_linear_loop_gives_its_run_back(run):
    cfg, rec = run
    sim = replay_op(cfg, rec)
    np.testing.assert_allclose(sim.pv, rec.pv, atol=1e-9)
    np.testing.assert_array_equal(sim.sp, rec.sp)


def test_the_closed_loop_replay_gives_its_run_back(run):
    cfg, rec = run
    sim = replay_sp(cfg, rec)
    np.testing.assert_allclose(sim.op, rec.op, atol=1e-9)
    np.testing.assert_allclose(sim.pv, rec.pv, atol=1e-9)


def test_op_range_maps_the_recordings_units_to_travel(run):
    cfg, rec = run
    counts = dataclasses.replace(cfg, valve=dataclasses.replace(cfg.valve, op_range=(4000.0, 27648.0)))
    raw = Recording(rec.t, rec.sp, 4000.0 + 236.48 * rec.op, None, rec.pv)
    np.testing.assert_allclose(op_travel(counts, raw.op), rec.op, atol=1e-9)
    np.testing.assert_allclose(replay_op(counts, raw).pv, rec.pv, atol=1e-9)


def test_bad_replays_are_refused_naming_the_recording(run):
    cfg, rec = run
    with pytest.raises(RecordingError, match="nosp.csv: no set point"):
        replay_sp(cfg, Recording(rec.t, None, rec.op, None, rec.pv, source="nosp.csv"))
    with pytest.raises(RecordingError, match=r"slow.csv: line 3: .*simulation.dt = 0.5 s"):
        replay_op(cfg, Recording(2.0 * rec.t, rec.sp, rec.op, None, rec.pv, source="slow.csv"))
    with pytest.raises(ValueError, match="no controller"):
        replay_sp(dataclasses.replace(cfg, controller=None), rec)


def test_a_read_only_replayed_input_reaches_the_time_loop_as_the_same_argument_types():
    """numba compiles a kernel once per argument type and a read-only array is a type of its own: a recording's
    read-only SP or OP (or a one-step run's held OP) must reach the compiled time loop as a writable array, the
    same numbers, or the loop is compiled a second time (seconds on a fresh cache)."""
    import numba

    bank = LoopBank([loop_from_mapping(LOOP)])
    sp = np.full((40, 1), 4.0)
    frozen = sp.copy()
    frozen.flags.writeable = False
    got = bank._replayed("sp", frozen, 40)
    assert numba.typeof(got) == numba.typeof(sp) and got.flags.writeable
    np.testing.assert_array_equal(got, sp)
    a, b = LoopBank([loop_from_mapping(LOOP)]), LoopBank([loop_from_mapping(LOOP)])
    np.testing.assert_array_equal(a.run(40, sp=frozen)["pv"], b.run(40, sp=sp)["pv"])
