"""A loop that starts in a given state (``valve.mv0``, ``valve.stuck0``, ``valve.initial_direction``,
``plant.rest_flow``): where a twin starts its recording.

Known truth: a loop run part-way reaches some state; a second loop started in that state and fed the rest of
the OP continues as the first one did.
"""

import dataclasses

import numpy as np
import pytest

from valve_emulator.config import ConfigError, loop_from_mapping
from valve_emulator.config.writer import loop_to_mapping
from valve_emulator.recordings.recording import Recording
from valve_emulator.simulation.loop import LoopBank
from valve_emulator.simulation.replay import replay_op

LOOP = {"name": "sticky", "valve": {"S": 4.0, "J": 1.5},
        "plant": {"num": [2.0], "den": [6.0, 1.0], "delay": 1.0, "pv0": 10.0, "u0": 50.0},
        "simulation": {"dt": 0.5, "duration": 200.0}}


def sticky(model: str, **valve) -> object:
    m = {**LOOP, "valve": {**LOOP["valve"], "model": model, **valve}}
    return loop_from_mapping(m)


def op_wave(n: int, seed: int) -> np.ndarray:
    """A wandering OP with reversals small and large (a valve sticks and slips on it)."""
    rng = np.random.default_rng(seed)
    return 50.0 + 8.0 * np.sin(np.arange(n) / 9.0) + np.cumsum(rng.normal(0.0, 0.4, n))


@pytest.mark.parametrize("model", ["kano", "he"])
@pytest.mark.parametrize("cut", [37, 80, 121, 160])
def test_a_valve_started_where_another_run_stood_continues_as_that_run(model, cut):
    """The valve's position, whether it is stuck and the direction it last moved in are its whole state: a
    valve started there (``mv0``, ``stuck0``, ``initial_direction``) moves as the one that got there did. (The
    literal Choudhury chart also remembers the sign of OP's last slope and whether it stopped on a flat OP,
    which these keys do not carry.)"""
    op = op_wave(240, seed=cut)
    whole = LoopBank([sticky(model)])
    whole.follow_external(True)
    head = whole.run(cut, op=op[:cut, None])
    tail = whole.run(op.size - cut, op=op[cut:, None])
    state = dict(mv0=float(head["mv"][-1, 0]), stuck0=bool(head["stuck"][-1, 0]))
    # the bank's direction after the head is read back from a fresh run to the same point
    again = LoopBank([sticky(model)])
    again.follow_external(True)
    again.run(cut, op=op[:cut, None])
    started = LoopBank([sticky(model, initial_direction=int(again.direction[0]), **state)])
    started.follow_external(True)
    rest = started.run(op.size - cut, op=op[cut:, None])
    np.testing.assert_array_equal(rest["mv"][:, 0], tail["mv"][:, 0])


def test_without_the_start_keys_a_loop_starts_as_it_always_did():
    """The default start, written out (the valve at rest at OP − d(S − J)/2, stuck; the plant at rest for that
    flow), gives the same run bit for bit."""
    plain = sticky("kano", op0=47.0, initial_direction=-1)
    written = sticky("kano", op0=47.0, initial_direction=-1, mv0=47.0 + 0.5 * (4.0 - 1.5), stuck0=True)
    written = dataclasses.replace(written, plant=dataclasses.replace(written.plant, rest_flow=47.0 + 1.25))
    op = op_wave(200, seed=3)
    runs = []
    for cfg in (plain, written):
        bank = LoopBank([cfg])
        bank.follow_external(True)
        runs.append(bank.run(op.size, op=op[:, None]))
    for key in ("mv", "pv", "flow", "stuck"):
        np.testing.assert_array_equal(runs[0][key], runs[1][key])


def test_a_plant_started_at_rest_for_another_flow_starts_at_its_pv_and_forgets_it():
    """``rest_flow``: PV starts at ``pv0 + G(0)(rest_flow − u0)`` and settles where the valve's flow takes it."""
    cfg = sticky("kano", S=0.0, J=0.0, op0=50.0)
    cfg = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, rest_flow=55.0))
    bank = LoopBank([cfg])
    assert bank.pv[0] == pytest.approx(10.0 + 2.0 * 5.0)
    bank.run(200)
    assert bank.pv[0] == pytest.approx(10.0, abs=1e-6)


def test_a_replay_of_a_loop_carrying_its_start_begins_there():
    """With ``mv0`` set, the open-loop replay starts the valve at that state (no mirrored pre-roll): a valve
    stuck at 40 % on an OP that never moves it more than S replays a flat 40 % travel."""
    cfg = sticky("kano", mv0=40.0, stuck0=True, initial_direction=1)
    t = np.arange(100) * 0.5
    op = 41.0 + 1.2 * np.sin(t / 3.0)   # stuck at OP 41.25: below its slip at 41.25 + J, above the reversal at − S
    rec = Recording(t, np.full(t.size, np.nan), op, None, np.zeros(t.size))
    sim = replay_op(cfg, rec)
    np.testing.assert_array_equal(sim.mv, 40.0)


@pytest.mark.parametrize("section, key, value, message", [
    ("valve", "mv0", 120.0, "valve.mv0 must be <= 100"),
    ("valve", "stuck0", "yes", "valve.stuck0 must be true or false"),
    ("plant", "rest_flow", "high", "plant.rest_flow must be a number"),
])
def test_bad_start_keys_are_refused_naming_the_key(section, key, value, message):
    m = {**LOOP, section: {**LOOP[section], key: value}}
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        loop_from_mapping(m)


def test_the_start_keys_are_written_and_read_back():
    cfg = sticky("kano", mv0=33.5, stuck0=False, initial_direction=-1)
    cfg = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, rest_flow=41.25))
    back = loop_from_mapping(loop_to_mapping(cfg))
    assert (back.valve.mv0, back.valve.stuck0, back.valve.initial_direction, back.plant.rest_flow) == \
        (33.5, False, -1, 41.25)
