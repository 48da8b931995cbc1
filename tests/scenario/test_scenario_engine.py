"""The scenario engine: on a device in this process, events act from the sample after their due tick, and the
old event form gives the device the same state over time as the malfunction form; over the registers, a fake
channel and a simulated clock record what the player writes and when, and the checks made before the first
event are seen to change nothing."""

from __future__ import annotations

import asyncio
import textwrap
from collections.abc import Sequence

import numpy as np
import pytest

from valve_emulator.device.registers import COMM_BASE, MAP_VERSION, N_REGISTERS, Status
from valve_emulator.device.roles import INSTRUCTOR
from valve_emulator.device.tick import Device
from valve_emulator.scenario import (
    DeviceMismatch,
    DevicePlayer,
    WriteRefused,
    due_ticks,
    follow,
    parse_scenario,
    play,
    probe,
    register_writes,
)
from valve_emulator.scenario.player import write_groups

DEVICE = """\
device:
  valve: {S: 5.0, J: 2.0}
  plant: {num: [1.0], den: [1.0, 0.0], pv_range: [-10.0, 10.0], noise: 0.5}
  controller: {kc: 0.4, ti: 2.0}
  device: {unit: 3, tick: 0.1}
duration: 100
"""

# tick 0.1 s: due ticks 0, round(10.4) = 10, round(25.6) = 26, 60; the end at 1000
TIMELINE = """\
- {at: 0, event: sp, value: 5.0}
- {at: 1.04, event: stiction, S: 3.5, J: 1.25, say: the packing binds}
- {at: 2.56, event: seize}
- {at: 6.0, event: normal}
"""


def scenario(events: str = TIMELINE, device: str = DEVICE):
    return parse_scenario(device + "events:\n" + textwrap.indent(textwrap.dedent(events), "  "), source="s.yaml")


class FakeDevice:
    """A register channel and a clock on one simulated tick counter: ``until`` jumps the counter forward."""

    where = "fake:502 unit 3"

    def __init__(self, *, now: int = 0, accept_after: int = 0, controller: bool = True,
                 version: int = MAP_VERSION, refuse_instructor: bool = False) -> None:
        self.now, self.accept_after, self.refuse_instructor = now, accept_after, refuse_instructor
        self.words = [0] * N_REGISTERS
        self.words[12] = int(Status.CONTROLLER) if controller else 0   # status
        self.words[13] = version                                       # map_version
        self.words[10:12] = [500, 200]                                 # S 5 %, J 2 % (scale 100)
        self.writes: list[tuple[int, int, list[int]]] = []             # (device tick, address, words)
        self.waits: list[int] = []

    async def read(self, address: int, count: int) -> Sequence[int]:
        return list(self.words[address:address + count])

    async def write(self, address: int, words: Sequence[int]) -> int:
        if self.refuse_instructor and address in (10, 11, 28, 29, 30):
            raise WriteRefused(f"write holding {address}: exception 0x02 (illegal data address)", address=address)
        self.now += self.accept_after
        self.writes.append((self.now, address, list(words)))
        self.words[address:address + len(words)] = list(words)
        return self.now

    async def tick(self) -> int:
        return self.now

    async def until(self, tick: int) -> int:
        self.waits.append(tick)
        self.now = max(self.now, tick)
        return self.now


def test_due_ticks_are_the_nearest_ticks_after_the_start():
    sc = scenario()
    assert [(due, ev.kind) for due, ev in due_ticks(sc.events, sc.dt, start_tick=100)] == [
        (100, "sp"), (110, "stiction"), (126, "seize"), (160, "clear")]


async def test_play_writes_each_event_at_its_due_tick_in_contiguous_runs():
    dev = FakeDevice(now=100)
    seen = []
    applied = await play(scenario(), dev, dev, start_tick=100, on_applied=seen.append)
    # sp 5.0 on pv_range -10..10 is 75 % -> 7500 at sp (5); S, J are adjacent (10, 11); normal restores
    # S 5 %, J 2 % and noise 0.5 of a range of 20 = 2.5 % -> 250, with load and fault 0 (28, 29, 30), and no
    # communication fault (the unit registers)
    assert dev.writes == [(100, 5, [7500]), (110, 10, [350, 125]), (126, 30, [1]),
                          (160, 10, [500, 200]), (160, 28, [0, 250, 0]), (160, COMM_BASE, [0, 0])]
    assert [(a.event.kind, a.due, a.tick, a.late) for a in applied] == [
        ("sp", 0, 0, 0), ("stiction", 10, 10, 0), ("seize", 26, 26, 0), ("clear", 60, 60, 0)]
    assert seen == applied
    assert dev.waits[-1] == 1100   # then it waits for the end of the scenario: 100 s after the start
    assert seen[1].line(0.1) == '[t =      1.0 s] stiction S=3.5 J=1.25 -- "the packing binds"'


async def test_a_late_write_is_reported_with_the_tick_the_device_accepted_it():
    dev = FakeDevice(accept_after=2)
    applied = await play(scenario("- {at: 1.0, event: seize}\n"), dev, dev)
    assert [(a.due, a.tick, a.late) for a in applied] == [(10, 12, 2)]
    assert applied[0].line(0.1).endswith("seize (late by 2 ticks)")


async def test_stop_ends_the_play_between_events_without_waiting_for_the_end():
    dev = FakeDevice()
    stop = asyncio.Event()
    applied = await play(scenario(), dev, dev, on_applied=lambda a: stop.set() if a.event.kind == "stiction" else None,
                         stop=stop)
    assert [a.event.kind for a in applied] == ["sp", "stiction"]
    assert [address for _, address, _ in dev.writes] == [5, 10]
    assert 1000 not in dev.waits


async def test_probe_writes_the_current_stiction_back_when_the_scenario_writes_instructor_registers():
    dev = FakeDevice(now=42)
    assert await probe(scenario(), dev) == 42
    assert dev.writes == [(42, 10, [500, 200])]   # the values it already had: nothing changes


async def test_probe_writes_nothing_when_no_event_needs_instructor_writes():
    dev = FakeDevice(now=7, refuse_instructor=True)
    assert await probe(scenario("- {at: 1, event: sp, value: 2.0}\n"), dev) == 7
    assert dev.writes == []


@pytest.mark.parametrize("device, message", [
    ({"version": MAP_VERSION + 1}, f"fake:502 unit 3: register map version {MAP_VERSION + 1}, this player needs"),
    ({"controller": False}, "fake:502 unit 3: the loop has no internal controller"),
    ({"refuse_instructor": True}, (r"fake:502 unit 3 refuses instructor writes \(write holding 10: exception 0x02 "
                                   r"\(illegal data address\)\); allow them with device.instructor_writes")),
])
async def test_probe_names_the_device_that_does_not_fit_and_writes_nothing(device, message):
    dev = FakeDevice(**device)
    before = list(dev.words)
    with pytest.raises(DeviceMismatch, match=message) as exc:
        await probe(scenario(), dev)
    assert exc.value.where == "fake:502 unit 3" and isinstance(exc.value, ValueError)
    assert dev.writes == [] and dev.words == before


# --- on a device in this process ------------------------------------------------------------------------

def _states(device: Device, ticks: int) -> list[np.ndarray]:
    """The loop's state in each of ``ticks`` samples -- PV, MV, OP and the S, J, load, noise and seizure the
    sample was computed with -- recorded after each tick, before the scenario acts."""
    out = []

    def record(dev: Device) -> None:
        b = dev.bank
        out.append(np.array([b.pv[0], b.mv[0], b.op[0], b.S[0], b.J[0], b.load[0], b.noise_std[0], b.frozen[0]]))

    device.on_tick.insert(0, record)
    device.advance(ticks)
    device.on_tick.remove(record)
    return out


def test_events_act_from_the_sample_after_their_due_tick():
    sc = scenario("- {at: 0, malfunction: {kind: seize}}\n- {at: 1.04, malfunction: {kind: stiction, S: 3.5}}\n")
    device = Device.from_config(sc.config, time_scale=0)
    seen = []
    player = follow(sc, device, on_applied=seen.append)
    assert device.bank.frozen[0]                      # due at tick 0: on before the first sample
    states = _states(device, 12)                      # samples 1..12: due at tick 10, acts from sample 11 on
    assert [s[3] for s in states[:10]] == [5.0] * 10 and [s[3] for s in states[10:]] == [3.5] * 2
    assert [(a.event.kind, a.due, a.tick) for a in seen] == [("seize", 0, 0), ("stiction", 10, 10)]
    assert player.finished and device.on_tick == []   # done: the device may batch its ticks again


def test_a_player_that_finishes_inside_a_tick_leaves_the_other_callbacks_of_that_tick_alone():
    sc = scenario("- {at: 0.5, malfunction: {kind: seize}}\n")
    device = Device.from_config(sc.config, time_scale=0)
    follow(sc, device)
    seen = []
    device.on_tick.append(lambda dev: seen.append(dev.ticks))   # after the player's hook, like a recorder
    device.advance(8)
    assert seen == list(range(1, 9))


OLD_FORM = """\
- {at: 1.0, event: stiction, S: 3.5, J: 1.25}
- {at: 2.0, event: sp, value: 2.0}
- {at: 8.0, event: load, flow: -2.5}
- {at: 9.0, event: noise, std: 1.5}
- {at: 12.0, event: seize}
- {at: 15.0, event: release}
- {at: 20.0, event: normal}
"""
NEW_FORM = """\
- {at: 1.0, malfunction: {kind: stiction, S: 3.5, J: 1.25}}
- {at: 2.0, sp: 2.0}
- {at: 8.0, malfunction: {kind: load, flow: -2.5}}
- {at: 9.0, malfunction: {kind: noise, std: 0.3}}
- {at: 12.0, malfunction: {kind: seize}}
- {at: 15.0, malfunction: {kind: release}}
- {at: 20.0, malfunction: {kind: clear}}
"""


def test_the_old_event_form_played_as_register_writes_and_the_malfunction_form_give_the_same_device_state():
    """The old player wrote the registers of each ``event:``; the engine now injects the malfunction. Both
    devices go through the same states, sample for sample, for every fault the old form had."""
    old, new = scenario(OLD_FORM), scenario(NEW_FORM)
    by_registers = Device.from_config(old.config, time_scale=0)

    def write_registers(event):   # the loop's registers (the unit's communication registers are the server's)
        loop_writes = [(name, word) for name, word in register_writes(event, old) if not name.startswith("comm_")]
        for address, words in write_groups(loop_writes):
            by_registers.write(0, address, words, role=INSTRUCTOR)

    DevicePlayer(old.events, old.dt, start_tick=0, apply=write_registers).attach(by_registers)
    injected = Device.from_config(new.config, time_scale=0)
    follow(new, injected)
    a, b = _states(by_registers, 300), _states(injected, 300)
    assert np.array_equal(np.array(a), np.array(b))
    assert a[130][7] == 1.0 and a[130][3:7].tolist() == [3.5, 1.25, -2.5, pytest.approx(0.3)]   # all on at 13 s
    assert a[-1][3:8].tolist() == [5.0, 2.0, 0.0, 0.5, 0.0]   # cleared: the configuration again
