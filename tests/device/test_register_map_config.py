"""A configured ``device.register_map``: what a file may say, what it is refused with, and that without one the
device serves the standard map exactly as before."""

import dataclasses
import struct
from pathlib import Path

import numpy as np
import pytest

from valve_emulator.config import ConfigError, load_server, server_from_mapping
from valve_emulator.device.registers import (
    INPUT_REGISTERS,
    REGISTERS,
    RegisterAddressError,
    RegisterValueError,
    Scaling,
    decode_write,
    encode_loop,
    encode_words,
    format_registers,
    registers_table,
)
from valve_emulator.device.registers.bits import COILS, DISCRETE_INPUTS
from valve_emulator.device.registers.mapping import STANDARD, register_map_of
from valve_emulator.device.registers.render import not_served
from valve_emulator.device.roles import INSTRUCTOR
from valve_emulator.device.tick import Device

PLANT = "plant:\n  fopdt: {gain: 1.0, tau: 5.0}\n  pv_range: [0.0, 200.0]\n"


def _write(tmp_path, tags, *, extra="", name="map.yaml"):
    """A single-loop config whose register_map has ``tags`` (YAML lines, indented under ``tags:``)."""
    text = PLANT + extra + "device:\n  register_map:\n    base: 1\n    tags:\n" + "".join(
        f"      {line}\n" for line in tags)
    path = tmp_path / name
    path.write_text(text)
    return path


def _refused(path):
    with pytest.raises(ConfigError) as info:
        cfg = load_server(path)
        register_map_of(cfg)
    return info.value


def _line_of(path, text):
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if text in line)


# --- what is refused, with the file, the line and the key ---------------------------------------------------

@pytest.mark.parametrize("tags, culprit, key, words", [
    (["op: {address: 40001, type: float32}", "mv: {address: 40002, type: uint16, raw: [0, 1000]}"],
     "mv:", "tags.mv.address", "overlaps device.register_map.tags.op"),
    (["op: {address: 465536, type: float32}"], "op:", "tags.op.address", "runs past address 65535"),
    (["op: {address: 465537, type: uint16}"], "op:", "tags.op.address", "past the last holding reference"),
    (["op: {address: 1, type: float32}"], "op:", "tags.op.type", "does not fit the coil table"),
    (["pv: {address: 40001, type: bits}"], "pv:", "tags.pv.type", "does not fit the holding table"),
    (["valve_position: {address: 40001, type: uint16}"], "valve_position:", "tags.valve_position",
     "is not a tag of the device"),
    (["op: {address: 40001, type: int16, raw: [100, 100]}"], "op:", "tags.op.raw", "lo != hi"),
    (["op: {address: 30001, type: int16, raw: [0, 27648]}"], "op:", "tags.op.address",
     "input registers are read-only"),
    (["stuck: {address: 1}"], "stuck:", "tags.stuck.address", "coils are written"),
    (["op: {address: 40001, type: int16, raw: [0, 40000]}"], "op:", "tags.op.raw", "int16 holds"),
    (["kc: {address: 40001, type: uint16, raw: [0, 1000]}"], "kc:", "tags.kc.raw", "range: [lo, hi]"),
    (["comm_fault: {address: 40001, type: uint16}"], "comm_fault:", "tags.comm_fault", "unit register"),
    (["pv_f32: {address: 465281, type: uint16, raw: [0, 100]}"], "pv_f32:", "tags.pv_f32.address",
     "unit register comm_fault"),
    (["op: {address: 40001}"], "op:", "tags.op.type", "missing key"),
])
def test_a_bad_map_is_refused_at_load_naming_file_line_and_key(tmp_path, tags, culprit, key, words):
    path = _write(tmp_path, tags)
    err = _refused(path)
    message = str(err)
    assert message.startswith(f"{path}:{_line_of(path, culprit)}: "), message
    assert f"device.register_map.{key}" in message and words in message


def test_a_configured_map_needs_one_loop_per_unit():
    with pytest.raises(ConfigError, match="each unit carries one loop"):
        server_from_mapping({"device": {"register_map": {"tags": {"op": {"address": 40001, "type": "uint16"}}}},
                             "fleet": {"count": 4, "loops_per_unit": 2,
                                       "base": {"plant": {"fopdt": {"gain": 1.0, "tau": 5.0}}}}})


def test_base_zero_takes_offsets_and_a_table(tmp_path):
    path = tmp_path / "zero.yaml"
    path.write_text(PLANT + "device:\n  register_map:\n    base: 0\n    tags:\n"
                            "      op: {address: 100, type: uint16}\n")
    err = _refused(path)
    assert "tags.op.table" in str(err) and "name the table" in str(err)
    path.write_text(PLANT + "device:\n  register_map:\n    base: 0\n    tags:\n"
                            "      op: {table: holding, address: 100, type: uint16}\n"
                            "      pv: {table: input, address: 0, type: float32}\n")
    regmap = register_map_of(load_server(path))
    assert [(r.name, r.table, r.address) for r in regmap.registers] == [("op", "holding", 100), ("pv", "input", 0)]
    rows = {r["name"]: r for r in registers_table(load_server(path))}
    assert rows["op"]["reference"] == "holding 100" and rows["pv"]["reference"] == "input 0"


# --- the standard map, bit for bit --------------------------------------------------------------------------

def test_without_a_register_map_the_standard_map_is_served():
    cfg = load_server(_default_config())
    assert cfg.device.register_map is None and register_map_of(cfg) is STANDARD
    assert STANDARD.holding == REGISTERS and STANDARD.input == INPUT_REGISTERS
    assert STANDARD.coils == COILS and STANDARD.discrete_inputs == DISCRETE_INPUTS
    # one section: the input table reads the holding words at the same address (the mirror)
    assert STANDARD.row_words == 32   # op_pct .. alarms
    assert all(STANDARD.word_offset(t, a) == a for t in ("holding", "input") for a in range(31))
    assert not_served(STANDARD) == []


def _default_config():
    from importlib import resources
    return resources.files("valve_emulator.data") / "default_device.yaml"


def test_the_standard_image_is_the_codec_rows_of_the_standard_map():
    """The device's served image without a map is the compiled kernel's, and the codec's rows of STANDARD equal
    it word for word: the standard map is one instance of the generic description, not a separate path."""
    rng = np.random.default_rng(7)
    n = 6
    scaling = Scaling.build(n, pv_range=(-10.0, 30.0), has_controller=[True, False] * 3, word_order="CDAB")

    class State:
        pass

    state = State()
    for name in ("op", "mv", "flow", "S", "J"):
        setattr(state, name, rng.uniform(-5, 105, n))
    for name in ("pv", "sp", "kc", "ti", "td", "load", "noise_std"):
        setattr(state, name, rng.uniform(-20, 40, n))
    for name in ("stuck", "sat_low", "sat_high", "auto", "frozen"):
        setattr(state, name, rng.uniform(size=n) < 0.5)
    state.has_controller = scaling.has_controller
    kernel = encode_words(state, scaling, tick=12345, overruns=3, time=1.25)
    codec = np.array([encode_loop(state, scaling, i, tick=12345, overruns=3, time=1.25, regmap=STANDARD)
                      for i in range(n)])
    assert np.array_equal(kernel, codec)


def test_a_device_without_a_map_serves_its_standard_image(fake_bank_cls):
    cfg = load_server(_default_config())
    device = Device.from_config(cfg, bank=fake_bank_cls.for_config(cfg), time_scale=0)
    assert device.served is device.image and device.served_layout is device.layout


# --- a configured map's rows and their codec ----------------------------------------------------------------

def _config(tags, **device):
    return server_from_mapping({"plant": {"fopdt": {"gain": 1.0, "tau": 5.0}, "pv_range": [0.0, 200.0]},
                                "device": {**device, "register_map": {"word_order": "CDAB", "tags": tags}}})


def test_counts_float_and_word_order_encode_as_configured():
    cfg = _config({"op": {"address": 40101, "type": "int16", "raw": [0, 27648]},
                   "pv": {"address": 30201, "type": "float32", "word_order": "ABCD"},
                   "mv": {"address": 30203, "type": "uint16", "raw": [6400, 32000]},
                   "sp_f32": {"address": 30204, "type": "float64"}})
    regmap, scaling = register_map_of(cfg), Scaling.from_config(cfg)

    class State:
        op, mv, flow, pv, sp, kc, ti, td, S, J = 25.0, 50.0, 10.0, 150.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0
        stuck = sat_low = sat_high = auto = False
        has_controller = False

    row = encode_loop(State(), scaling, 0, tick=0, overruns=0, time=0.0, regmap=regmap)
    holding = lambda a: row[regmap.word_offset("holding", a)]  # noqa: E731
    words = lambda a, k: [int(w) for w in row[regmap.word_offset("input", a):regmap.word_offset("input", a) + k]]  # noqa: E731
    assert holding(100) == 6912                                                  # 25 % of 27648
    assert struct.unpack(">f", struct.pack(">HH", *words(200, 2)))[0] == 150.0   # ABCD: high word first
    assert words(202, 1) == [6400 + 25600 // 2]                                  # 12 mA
    assert words(203, 4) == [0, 0, 0, 0]                                         # no controller: sp reads 0


def test_writes_outside_the_raw_range_are_refused_and_inside_decode_to_engineering_units():
    cfg = _config({"op": {"address": 40001, "type": "uint16", "raw": [6400, 32000]},
                   "S": {"address": 40002, "type": "float32"}})
    regmap, scaling = register_map_of(cfg), Scaling.from_config(cfg)
    assert decode_write(0, [19200], scaling, 0, regmap=regmap) == [("op", pytest.approx(50.0))]
    with pytest.raises(RegisterValueError, match="register op: 32001 out of range 6400..32000"):
        decode_write(0, [32001], scaling, 0, regmap=regmap)
    high, low = struct.unpack(">HH", struct.pack(">f", 7.5))
    assert decode_write(1, [low, high], scaling, 0, regmap=regmap, role=INSTRUCTOR) == [("S", 7.5)]   # CDAB
    high, low = struct.unpack(">HH", struct.pack(">f", 150.0))
    with pytest.raises(RegisterValueError, match="out of range"):
        decode_write(1, [low, high], scaling, 0, regmap=regmap, role=INSTRUCTOR)   # S is 0..100 %
    with pytest.raises(RegisterAddressError, match="write all its 2 registers"):
        decode_write(1, [0], scaling, 0, regmap=regmap, role=INSTRUCTOR)


def test_registers_lists_a_configured_map_in_its_base_and_says_what_it_does_not_serve():
    cfg = _config({"op": {"address": 40101, "type": "int16", "raw": [0, 27648]},
                   "pv": {"address": 30201, "type": "float32"}, "auto": [{"address": 1}, {"address": 10001}]})
    rows = registers_table(cfg)
    by_name = {(r["name"], r["table"]): r for r in rows}
    assert by_name[("op", "holding")]["reference"] == "40101" and by_name[("op", "holding")]["address"] == 100
    assert by_name[("op", "holding")]["scale"] == "raw 0..27648 = 0..100"
    assert by_name[("pv", "input")]["word_order"] == "CDAB"
    assert by_name[("auto", "coil")]["reference"] == "00001"
    assert by_name[("auto", "discrete_input")]["reference"] == "10001"
    assert ("op_pct", "holding") not in by_name and ("step", "holding") in by_name   # the clock stays
    missing = not_served(register_map_of(cfg))
    assert "op_pct" in missing and "mv" in missing and "op" not in missing and "auto" not in missing
    assert "| op " in format_registers(rows, "md")


def _random_state(rng, n, scaling):
    class State:
        pass

    state = State()
    for name in ("op", "mv", "flow", "S", "J"):
        setattr(state, name, rng.uniform(-20, 120, n))
    for name in ("pv", "sp", "kc", "ti", "td", "load", "noise_std"):
        setattr(state, name, rng.uniform(-300, 500, n))
    state.pv[:3] = (np.nan, np.inf, -1e40)            # what a broken sensor or a diverging loop reads as
    state.ti[:2] = (0.0, np.inf)                      # no integral action
    for name in ("stuck", "sat_low", "sat_high", "auto", "frozen"):
        setattr(state, name, rng.uniform(size=n) < 0.5)
    state.has_controller = scaling.has_controller
    return state


EVERY_KIND = {"op": {"address": 40001, "type": "int16", "raw": [0, 27648]},
              "op_ma": {"address": 40002, "type": "uint16"},
              "sp": {"address": 40003, "type": "float64", "word_order": "ABCD"},
              "mode": {"address": 40007, "type": "uint16"},
              "ti": {"address": 40008, "type": "uint16"},
              "kc": {"address": 40009, "type": "int32", "raw": [-1000, 1000000], "range": [-1.0, 1000.0]},
              "pv": {"address": 30001, "type": "uint16", "raw": [6400, 32000]},
              "pv_f32": {"address": 30002, "type": "float32"},
              "sp_f32": {"address": 30004, "type": "int16", "raw": [0, 27648]},
              "noise": {"address": 30005, "type": "uint32"},
              "load": {"address": 30007, "type": "int16"},
              "status": {"address": 30008, "type": "uint16"},
              "tick": {"address": 30009, "type": "uint32", "word_order": "ABCD"},
              "time": {"address": 30011, "type": "float32"}}


@pytest.mark.parametrize("source", ["s7_analog", "modicon_float_cdab", "ma_4_20_counts", "every kind"])
def test_all_loops_at_once_encode_as_each_loop_alone(source):
    """The device's per-tick pass over a configured map (numpy columns) gives the codec's words, loop by loop."""
    from valve_emulator.device.registers.columns import encode_rows

    if source == "every kind":
        cfg = server_from_mapping({"device": {"register_map": {"word_order": "CDAB", "tags": EVERY_KIND}},
                                   "loops": [{"unit": u, "plant": {"fopdt": {"gain": 1.0, "tau": 5.0},
                                                                   "pv_range": [-50.0 * u, 100.0 * u]},
                                              **({"controller": {"kc": 1.0}} if u % 2 else {})}
                                             for u in range(1, 9)]})
    else:   # the profile's loop on eight units
        cfg = load_server(Path(__file__).resolve().parents[2] / "configs" / "profiles" / f"{source}.yaml")
        loop = cfg.loops[0]
        cfg = dataclasses.replace(cfg, loops=tuple(dataclasses.replace(loop, device=dataclasses.replace(
            loop.device, unit=u)) for u in range(1, 9)))
    regmap, scaling = register_map_of(cfg), Scaling.from_config(cfg)
    state = _random_state(np.random.default_rng(11), scaling.n, scaling)
    rows = encode_rows(state, scaling, regmap, tick=2 ** 32 + 5, overruns=7, time=12.3)
    one_by_one = np.array([encode_loop(state, scaling, i, tick=2 ** 32 + 5, overruns=7, time=12.3, regmap=regmap)
                           for i in range(scaling.n)])
    assert np.array_equal(rows, one_by_one)


def test_a_configured_map_serves_the_alarm_word_after_a_tick_and_after_an_acknowledgement():
    """PV starts at 0, below the low alarm limit (10 % of the PV range): the served ``alarms`` tag reads
    PV_LOW | UNACKED after a tick, and PV_LOW alone once the alarm is acknowledged between ticks, as the standard
    image does."""
    from valve_emulator.device.registers import AlarmBit, address_of

    cfg = _config({"op": {"address": 40001, "type": "int16", "raw": [0, 27648]},
                   "alarms": {"address": 30010, "type": "uint16"}})
    dev = Device.from_config(cfg)
    at = 2 * dev.register_map.word_offset("input", 9)
    served = lambda: int.from_bytes(dev.served[at:at + 2], "big")  # noqa: E731
    standard = lambda: int.from_bytes(dev.image[2 * address_of("alarms"):2 * address_of("alarms") + 2], "big")  # noqa: E731
    dev.tick()
    assert served() == standard() == AlarmBit.PV_LOW | AlarmBit.UNACKED
    assert dev.alarms.acknowledge(0)
    assert served() == standard() == AlarmBit.PV_LOW
