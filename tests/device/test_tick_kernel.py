"""A tick in one compiled call (the loop bank's step and the image encoding together) against the two calls it
replaces: the same register image and the same bank state after every tick, whatever acts between the ticks."""

import numpy as np
import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import address_of
from valve_emulator.device.roles import INSTRUCTOR
from valve_emulator.device.tick import Device

LOOPS = [
    {"unit": 1, "valve": {"S": 5.0, "J": 2.0},
     "plant": {"fopdt": {"gain": 3.0, "tau": 10.0, "delay": 1.0}, "noise": 0.05,
               "disturbance": {"type": "sine", "amplitude": 2.0, "period": 5.0}},
     "controller": {"kc": 0.2, "ti": 10.0, "sp_steps": [[0.5, 1.0], [3.0, 2.0]]}},
    {"unit": 2, "valve": {"model": "kano", "S": 3.0, "J": 1.0, "actuator_lag": 0.4},
     "plant": {"num": [1.0], "den": [6.0, 5.0, 1.0], "delay": 0.25, "pv0": 20.0}},
    {"unit": 3, "valve": {"model": "he", "S": 2.0, "J": 0.5, "flow_limits": [5.0, 90.0]},
     "plant": {"integrator": {"gain": 0.1}, "pv0": 50.0},
     "controller": {"kc": 1.5, "ti": 4.0, "td": 0.5, "mode": "manual"}},
]


def _devices():
    """Two devices of the same three loops: one ticks in one compiled call, the other steps, then encodes."""
    config = server_from_mapping({"device": {"tick": 0.1, "instructor_writes": True}, "loops": LOOPS})
    one, two = (Device.from_config(config, time_scale=0.0) for _ in range(2))
    assert one._step_encode is not None
    two._step_encode = None
    return one, two


def _same(one: Device, two: Device) -> None:
    assert bytes(one.image) == bytes(two.image)
    state_one, state_two = one.bank.state(), two.bank.state()
    assert state_one.keys() == state_two.keys()
    for key, value in state_one.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, state_two[key], err_msg=key)
        else:
            assert value == state_two[key], key


def test_a_tick_in_one_call_gives_the_image_and_state_of_a_step_then_an_encoding():
    """Writes of OP, set point, mode, tuning, stiction, load and a seized valve between single ticks (the
    lockstep ``step`` = 1), across set-point steps and the first noisy sample: identical bytes and state."""
    one, two = _devices()
    writes = {3: (1, "op_pct", 6000), 7: (0, "sp", 7000), 11: (2, "op_pct", 2500), 15: (0, "kc", 500),
              19: (1, "S", 450), 23: (0, "load", 300), 27: (1, "fault", 1), 31: (2, "mode", 1)}
    for k in range(60):
        if k in writes:
            index, name, raw = writes[k]
            for device in (one, two):
                device.write(index, address_of(name), [raw], role=INSTRUCTOR)
        for device in (one, two):
            device.advance(1)
        _same(one, two)
    assert one.ticks == 60 and one.bank.k == 60


def test_a_tick_that_fails_in_one_call_fails_as_a_step_then_an_encoding_does():
    """A non-finite plant input stops the tick: the same error, tick count, image and state either way."""
    one, two = _devices()
    for device in (one, two):
        device.advance(2)
        device.bank.load[1] = np.inf   # past the setter's check, as only a defect could
        with pytest.raises(ValueError, match="non-finite"):
            device.advance(1)
        assert device.ticks == 2
    _same(one, two)


def test_the_bank_attributes_are_the_rows_the_compiled_step_reads():
    """A change through an attribute (or a snapshot restored in place) is what the next step sees."""
    one, _ = _devices()
    bank = one.bank
    floats = bank.packed.floats
    assert np.shares_memory(bank.op_external, floats) and np.shares_memory(bank._pid._kc, floats)
    assert np.shares_memory(bank._plant._head, bank.packed.ints)
    one.advance(40)   # past the set-point steps
    saved = bank.state()
    one.advance(5)
    after = bytes(one.image)
    bank.set_state(saved)
    one.ticks = 40
    one.advance(5)
    assert bytes(one.image) == after
