"""A one-word write accepted from the tables of its address does what the register codec says, and leaves every
write it does not accept to the general way untouched."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import N_REGISTERS, RegisterError, address_of, decode_write, patch
from valve_emulator.device.registers.mapping import STANDARD
from valve_emulator.device.roles import INSTRUCTOR, OPERATOR, UNAUTHENTICATED, VIEWER
from valve_emulator.device.runtime import load_server_or_default
from valve_emulator.device.tick import Device

PROFILES = Path(__file__).resolve().parents[2] / "configs" / "profiles"
WORDS = (0, 1, 450, 4000, 10000, 12001, 32767, 32768, 65535)
ROLES = (None, UNAUTHENTICATED, VIEWER, OPERATOR, INSTRUCTOR)


def _config(register_map=None):
    device = {"tick": 0.1, "instructor_writes": True, **({"register_map": register_map} if register_map else {})}
    return server_from_mapping({
        "device": device,
        "loops": [
            {"unit": 1, "valve": {"S": 5.0, "J": 2.0}, "plant": {"fopdt": {"gain": 3.0, "tau": 10.0}},
             "controller": {"kc": 0.2, "ti": 10.0, "mode": "manual", "op_limits": [5.0, 95.0]}},
            {"unit": 2, "valve": {"S": 3.0, "J": 1.0, "ma_table": [[4.0, 100.0], [20.0, 0.0]]},
             "plant": {"integrator": {"gain": 0.1}, "pv0": 50.0, "pv_range": [-20.0, 80.0]}},
        ]})


def _row(device, index):
    start = int(device.offsets[index])
    return np.frombuffer(device.image, ">u2", N_REGISTERS, start).astype(np.int64)


@pytest.mark.parametrize("index", [0, 1])
def test_an_accepted_one_word_write_queues_and_shows_what_the_codec_decodes_and_patches(index):
    accepted = set()
    config = _config()   # validated once (a frozen record): each case still gets a device of its own
    for address, word, role in itertools.product(range(N_REGISTERS), WORDS, ROLES):
        device = Device.from_config(config, time_scale=0)
        before = _row(device, index)
        if device.write_served_word(index, address, word, role=role):
            auto = bool(device.scaling.has_controller[index]) and device.effective_auto(index)
            changes = decode_write(address, [word], device.scaling, index, role=role, auto=auto)
            assert device._pending == {(index, q): v for q, v in changes}, (address, word, role)
            expected = before.copy()
            for quantity, value in changes:
                patch(expected, quantity, value, device.scaling, index)
            assert _row(device, index).tolist() == expected.tolist(), (address, word, role)
            accepted.add(changes[0][0])
        else:
            assert not device._pending and _row(device, index).tolist() == before.tolist(), (address, word, role)
    # the writes a lockstep or SCADA client repeats are the ones accepted this way
    assert {"op", "S", "J"} <= accepted and ("sp" in accepted) == (index == 0)


def test_a_write_the_tables_do_not_accept_is_refused_as_before():
    device = Device.from_config(_config(), time_scale=0)
    op = address_of("op_pct")   # OP of loop 0 is writable only in manual, within its op_limits
    assert not device.write_served_word(0, op, 9600)
    with pytest.raises(RegisterError, match="out of range 500..9500"):
        device.write_served(0, op, [9600])
    device.write(0, address_of("mode"), [1])       # auto
    assert not device.write_served_word(0, op, 5000)
    with pytest.raises(RegisterError, match="only while the controller is in manual"):
        device.write_served(0, op, [5000])
    assert not device.write_served_word(1, op, 5000, role=VIEWER)
    with pytest.raises(RegisterError, match="not writable by role 'viewer'"):
        device.write_served(1, op, [5000], role=VIEWER)


def test_a_configured_map_shows_an_accepted_write_in_both_images_as_the_general_way_does():
    """The Modicon profile's op_ma tag (mA x 1000, one word) writes OP: the served map's float32 and mA words and
    the standard image's three OP registers all show it."""
    config = load_server_or_default(PROFILES / "modicon_float_cdab.yaml")
    planned, general = (Device.from_config(config, time_scale=0) for _ in range(2))
    address = general.register_map.written("op").address   # the float32 op tag: two words, the general way
    op_ma = next(r for r in general.register_map.showing("op") if r.width == 1)
    assert not planned.write_served_word(0, address, 0x4000)
    for word in (4000, 12000, 17350, 20000):
        assert planned.write_served_word(0, op_ma.address, word)
        changes = decode_write(op_ma.address, [word], general.scaling, 0, regmap=general.register_map)
        general._patch(general.image, int(general.offsets[0]), STANDARD, changes, 0)
        general._patch(general.served, int(general.served_layout.offsets[0]), general.register_map, changes, 0)
        assert bytes(planned.image) == bytes(general.image) and bytes(planned.served) == bytes(general.served)
