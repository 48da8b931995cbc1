"""Register map: layout, encode/decode round trips, range and access errors, renderings."""

import csv
import io
import json
import math
import struct
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from valve_emulator.config import server_from_mapping
from valve_emulator.device import registers as reg
from valve_emulator.device.registers import (
    N_REGISTERS,
    RegisterAccessError,
    RegisterAddressError,
    RegisterValueError,
    Scaling,
    Status,
    address_of,
    check_read,
    decode_write,
    encode,
    format_registers,
    patch,
    registers_table,
)
from valve_emulator.device.roles import INSTRUCTOR


def _state(n=1, **over):
    """Loop-bank-shaped state arrays for ``n`` units (a test double of LoopBank's read side)."""
    base = dict(op=[37.5] * n, mv=[36.0] * n, flow=[36.0] * n, pv=[1.25] * n, sp=[2.5] * n,
                kc=[0.2] * n, ti=[10.0] * n, td=[0.0] * n, S=[5.0] * n, J=[2.0] * n,
                stuck=[True] * n, sat_low=[False] * n, sat_high=[False] * n,
                has_controller=[True] * n, auto=[True] * n)
    base.update(over)
    return SimpleNamespace(**{k: np.asarray(v) for k, v in base.items()})


def _words(state, scaling, **kw):
    kw = {"tick": 7, "overruns": 0, "time": 12.5, **kw}
    return encode(state, scaling, **kw)


def test_required_registers_exist_in_holding_table_and_op_is_writable():
    rows = {(r["name"], r["table"]): r for r in registers_table()}
    for name in ("op_pct", "op_ma", "mv_pct", "pv"):
        assert (name, "holding") in rows
    assert rows[("op_pct", "holding")]["access"] == "RW"
    assert rows[("op_ma", "holding")]["access"] == "RW"
    assert rows[("mv_pct", "holding")]["access"] == "R"
    # read-only values are mirrored as input registers at the same address, writable ones are not
    assert rows[("mv_pct", "input")]["address"] == rows[("mv_pct", "holding")]["address"]
    assert ("op_pct", "input") not in rows


def test_addresses_do_not_overlap_and_fill_the_map():
    used = [a for r in reg.REGISTERS for a in range(r.address, r.address + r.width)]
    assert sorted(used) == list(range(N_REGISTERS))


def test_json_rows_have_exactly_the_documented_keys():
    rows = json.loads(format_registers(registers_table(), "json"))
    assert rows and all(set(r) == {"name", "table", "address", "reference", "type", "scale", "units", "access"}
                        for r in rows)
    assert {r["type"] for r in rows} <= {"uint16", "int16", "uint32", "float32", "bit"}
    assert {r["table"] for r in rows} == {"holding", "input", "coil", "discrete_input"}
    assert {r["access"] for r in rows} <= set(reg.ACCESS_VALUES)


def test_csv_and_md_render_the_same_rows():
    rows = registers_table()
    parsed = list(csv.DictReader(io.StringIO(format_registers(rows, "csv"))))
    assert [r["name"] for r in parsed] == [r["name"] for r in rows]
    md = format_registers(rows, "md").splitlines()
    assert len(md) == len(rows) + 2 and md[0].startswith("| name")
    with pytest.raises(ValueError, match="fmt"):
        format_registers(rows, "xml")


def test_every_entry_shows_the_one_based_reference_of_its_table():
    by = {(r["name"], r["table"]): r["reference"] for r in registers_table()}
    assert by[("op_pct", "holding")] == "40001" and by[("fault", "holding")] == "40031"
    assert by[("pv", "input")] == "30005"
    assert by[("auto", "coil")] == "00001" and by[("seized", "coil")] == "00002"
    assert by[("stuck", "discrete_input")] == "10001" and by[("seized", "discrete_input")] == "10007"
    assert reg.bits.reference("holding", 65280) == "465281"          # six digits past 9999


def test_discrete_input_k_is_status_bit_k_and_coils_write_registers():
    names = [b.name for b in reg.bits.DISCRETE_INPUTS]
    assert names == ["stuck", "moving", "sat_low", "sat_high", "controller", "auto", "seized"]
    assert all(b.status == 1 << b.address for b in reg.bits.DISCRETE_INPUTS)
    assert reg.bits.coil_write(0, True) == (address_of("mode"), 1)
    assert reg.bits.coil_write(1, False) == (address_of("fault"), 0)
    assert reg.bits.bit_values(reg.bits.BitTable.DISCRETE_INPUT, 0b0110001, 4, 3) == [True, True, False]
    with pytest.raises(reg.RegisterAddressError, match="coil 1..2 outside the coil table 0..1"):
        reg.bits.check_bits(reg.bits.BitTable.COIL, 1, 2)
    assert reg.bits.check_bits(reg.bits.BitTable.COIL, 65, 1, blocks=3) == (2, 1)   # loop 2's seized coil


def test_module_docstring_table_is_the_generated_one():
    holding = [r for r in registers_table() if r["table"] == "holding"]
    generated = "".join("    " + line + "\n" for line in format_registers(holding, "md").splitlines())
    assert generated in reg.__doc__


def test_table_takes_pv_units_from_config():
    cfg = server_from_mapping({"loops": [{"unit": 3, "plant": {"num": [1.0], "den": [1.0, 1.0],
                                                                "units": "kg/m3"}}]})
    rows = {(r["name"], r["table"]): r for r in registers_table(cfg)}
    assert rows[("pv_f32", "holding")]["units"] == "kg/m3"


def test_encode_scales_every_quantity():
    sc = Scaling.build(1, pv_range=(-10.0, 10.0), has_controller=True)
    w = _words(_state(), sc)[0]
    assert w[address_of("op_pct")] == 3750
    assert w[address_of("op_ma")] == 10000                     # 4 + 0.16·37.5 mA
    assert w[address_of("mv_pct")] == 3600
    assert w[address_of("pv")] == 5625                         # (1.25 + 10)/20 · 10000
    assert w[address_of("sp")] == 6250
    assert w[address_of("kc")] == 200 and w[address_of("ti")] == 100 and w[address_of("td")] == 0
    assert w[address_of("S")] == 500 and w[address_of("J")] == 200
    assert w[address_of("status")] == Status.STUCK | Status.CONTROLLER | Status.AUTO
    assert w[address_of("map_version")] == reg.MAP_VERSION
    assert (w[14] << 16 | w[15]) == 7
    regs = [int(x) for x in w[18:28]]
    floats = struct.unpack(">5f", struct.pack(">10H", *regs))
    assert floats == pytest.approx((12.5, 37.5, 36.0, 1.25, 2.5))


def test_word_order_cdab_swaps_words_of_32_bit_values():
    abcd = _words(_state(), Scaling.build(1, word_order="ABCD"), tick=0x12345678)[0]
    cdab = _words(_state(), Scaling.build(1, word_order="CDAB"), tick=0x12345678)[0]
    assert list(abcd[14:16]) == [0x1234, 0x5678] and list(cdab[14:16]) == [0x5678, 0x1234]
    assert list(abcd[20:22]) == list(cdab[21:19:-1])
    assert list(abcd[:14]) == list(cdab[:14])


def test_controller_registers_read_zero_without_controller_and_pv_clips_to_int16():
    sc = Scaling.build(2, pv_range=(0.0, 1.0))
    st_ = _state(2, has_controller=[False, False], auto=[False, False], pv=[-1000.0, 1000.0])
    w = _words(st_, sc)
    assert (w[:, address_of("sp")] == 0).all() and (w[:, address_of("kc")] == 0).all()
    assert (w[:, address_of("mode")] == 0).all()
    assert w[0, address_of("pv")] == 0x8000 and w[1, address_of("pv")] == 0x7FFF   # int16 limits
    assert w[0, address_of("status")] & Status.CONTROLLER == 0


def test_p_only_controller_reads_ti_zero_and_writing_zero_means_no_integral():
    sc = Scaling.build(1, has_controller=True)
    w = _words(_state(ti=[math.inf]), sc)[0]
    assert w[address_of("ti")] == 0
    assert decode_write(address_of("ti"), [0], sc, 0) == [("ti", math.inf)]


@given(st.integers(0, 10000))
def test_op_pct_write_round_trips_through_op_ma(raw):
    sc = Scaling.build(1)
    [(q, op)] = decode_write(address_of("op_pct"), [raw], sc, 0)
    assert q == "op" and op == raw / 100
    row = _words(_state(op=[op]), sc)[0]
    assert row[address_of("op_pct")] == raw
    [(_, op_back)] = decode_write(address_of("op_ma"), [int(row[address_of("op_ma")])], sc, 0)
    assert op_back == pytest.approx(op, abs=0.01)   # op_ma resolution: 1 µA = 1/160 %


@given(st.integers(4000, 20000))
def test_op_ma_write_round_trips_with_default_table(raw):
    sc = Scaling.build(1)
    [(_, op)] = decode_write(address_of("op_ma"), [raw], sc, 0)
    row = np.zeros(N_REGISTERS, dtype=np.int64)
    patch(row, "op", op, sc, 0)
    assert row[address_of("op_ma")] == raw
    assert row[address_of("op_pct")] == round(op * 100)


def test_reverse_acting_ma_table_converts_and_limits_the_writable_current():
    sc = Scaling.build(1, ma_table=[[4.0, 100.0], [20.0, 0.0]])    # air-to-close valve
    [(_, op)] = decode_write(address_of("op_ma"), [8000], sc, 0)
    assert op == pytest.approx(75.0)
    row = _words(_state(op=[75.0]), sc)[0]
    assert row[address_of("op_ma")] == 8000
    narrow = Scaling.build(1, ma_table=[[4.0, -25.0], [20.0, 175.0]])   # 0..100 % = 6..14 mA
    assert list(narrow.ma_raw_range[0]) == [6000, 14000]
    with pytest.raises(RegisterValueError, match=r"register op_ma: 5999 out of range 6000..14000"):
        decode_write(address_of("op_ma"), [5999], narrow, 0)


def test_sp_write_converts_from_percent_of_range():
    sc = Scaling.build(1, pv_range=(-10.0, 10.0), has_controller=True)
    assert decode_write(address_of("sp"), [7500], sc, 0) == [("sp", pytest.approx(5.0))]


def test_out_of_range_write_names_the_register():
    sc = Scaling.build(1, has_controller=True)
    with pytest.raises(RegisterValueError, match=r"^register op_pct: 12000 out of range 0..10000$"):
        decode_write(address_of("op_pct"), [12000], sc, 0)
    with pytest.raises(RegisterValueError, match=r"register sp: -1 out of range 0..10000"):
        decode_write(address_of("sp"), [0xFFFF], sc, 0)
    with pytest.raises(RegisterValueError, match=r"register kc: 0 out of range"):
        decode_write(address_of("kc"), [0], sc, 0)


def test_multi_register_write_is_checked_completely_first():
    sc = Scaling.build(1, has_controller=True)
    with pytest.raises(RegisterValueError, match="register mode"):
        decode_write(address_of("sp"), [5000, 2], sc, 0, auto=False)   # sp fine, mode 2 bad
    assert decode_write(address_of("op_pct"), [1000, 8000], sc, 0) == [("op", 10.0), ("op", 25.0)]


def test_access_rules():
    with_ctl, without = Scaling.build(1, has_controller=True), Scaling.build(1, has_controller=False)
    with pytest.raises(RegisterAccessError, match="register mv_pct .* read-only"):
        decode_write(address_of("mv_pct"), [1], without, 0)
    with pytest.raises(RegisterAccessError, match="register sp .* needs an internal controller"):
        decode_write(address_of("sp"), [1], without, 0)
    with pytest.raises(RegisterAccessError, match="register S .* role 'unauthenticated'"):
        decode_write(address_of("S"), [300], without, 0)
    assert decode_write(address_of("S"), [300, 150], without, 0, role=INSTRUCTOR) == [("S", 3.0), ("J", 1.5)]
    with pytest.raises(RegisterAccessError, match="register op_pct .* manual"):
        decode_write(address_of("op_pct"), [1], with_ctl, 0, auto=True)
    assert decode_write(address_of("op_pct"), [100], with_ctl, 0, auto=False) == [("op", 1.0)]
    with pytest.raises(RegisterAddressError, match="outside the map"):
        decode_write(N_REGISTERS - 1, [0, 0], without, 0)


def test_check_read_respects_map_end_and_input_holes():
    check_read("holding", 0, N_REGISTERS)
    check_read("input", address_of("status"), N_REGISTERS - address_of("status"))
    check_read("input", address_of("mv_pct"), 3)
    with pytest.raises(RegisterAddressError):
        check_read("holding", N_REGISTERS - 1, 2)
    with pytest.raises(RegisterAddressError, match="unmapped"):
        check_read("input", 0, 1)                       # op_pct is writable: not an input register
    with pytest.raises(RegisterAddressError, match="unmapped"):
        check_read("input", address_of("mv_pct"), 4)    # runs into sp


def test_patch_matches_a_full_encode():
    sc = Scaling.build(1, pv_range=(-10.0, 10.0), has_controller=True, word_order="CDAB")
    before = _words(_state(), sc)[0]
    after = _words(_state(op=[61.25], sp=[-3.0], auto=[False], kc=[1.5], S=[3.0]), sc)[0]
    row = before.copy()
    for q, v in (("op", 61.25), ("sp", -3.0), ("auto", False), ("kc", 1.5), ("S", 3.0)):
        patch(row, q, v, sc, 0)
    assert list(row) == list(after)


def test_scaling_from_config_uses_each_loop():
    cfg = server_from_mapping({"device": {"word_order": "CDAB"}, "loops": [
        {"unit": 1, "plant": {"num": [1.0], "den": [1.0, 1.0], "pv_range": [0.0, 50.0]}},
        {"unit": 2, "plant": {"num": [1.0], "den": [1.0, 0.0]}, "controller": {"kc": 0.4, "ti": 2.0},
         "valve": {"ma_table": [[4.0, 100.0], [20.0, 0.0]]}}]})
    sc = Scaling.from_config(cfg)
    assert sc.n == 2 and sc.word_order == "CDAB"
    assert list(sc.has_controller) == [False, True]
    assert (sc.pv_lo[0], sc.pv_hi[0]) == (0.0, 50.0)
    assert sc.op_to_ma(np.array([25.0, 25.0])) == pytest.approx([8.0, 16.0])


def test_nan_reads_as_the_bottom_of_the_range_not_garbage():
    sc = Scaling.build(1, has_controller=True)
    w = _words(_state(mv=[math.nan], pv=[math.nan]), sc)[0]
    assert w[address_of("mv_pct")] == 0 and w[address_of("pv")] == 0x8000
    assert math.isnan(struct.unpack(">f", struct.pack(">2H", *map(int, w[22:24])))[0])   # float keeps NaN
