"""The register table drives the codec: round trips at every register's scale, both word orders, the
compiled encoder against the plain-Python one, ``patch`` against a full re-encode, the clients' decoders."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from valve_emulator.clients import _modbus
from valve_emulator.config import schema
from valve_emulator.device import registers as reg
from valve_emulator.device.registers import (
    INPUT_REGISTERS,
    REGISTERS,
    WRITABLE_QUANTITIES,
    Conversion,
    DataType,
    Scaling,
    decode_value,
    decode_write,
    encode,
    encode_loop,
    encode_value,
    from_words,
    patch,
    write_range,
)
from valve_emulator.device.roles import INSTRUCTOR

SLOW = settings(deadline=None, max_examples=60)   # the first example may compile the kernel
SIXTEEN = [r for r in REGISTERS if r.width == 1]
THIRTY_TWO = [r for r in REGISTERS if r.width == 2]
WRITABLE = [r for r in REGISTERS if r.access is not reg.R]
REVERSE_MA = ((4.0, 100.0), (20.0, 0.0))   # an air-to-close valve
pv_ranges = st.tuples(st.floats(-1e3, 1e3), st.floats(0.01, 1e3)).map(lambda lw: (lw[0], lw[0] + lw[1]))


def _scaling(n=1, **kw):
    return Scaling.build(n, **{"has_controller": True, **kw})


# --- one definition --------------------------------------------------------------------------------------

def test_word_order_and_address_space_have_one_definition():
    assert reg.ABCD is schema.WordOrder.ABCD and reg.CDAB is schema.WordOrder.CDAB
    assert _modbus.ABCD is reg.ABCD and _modbus.CDAB is reg.CDAB
    assert reg.MAX_BLOCKS is schema.MAX_BLOCKS and reg.BLOCK_STRIDE is schema.BLOCK_STRIDE
    assert reg.MAX_BLOCKS * reg.BLOCK_STRIDE == 0x10000 and reg.N_REGISTERS <= reg.BLOCK_STRIDE
    assert {t.value: (t.width, t.struct_format) for t in DataType} == _modbus.TYPES


def test_rows_are_consistent():
    for r in REGISTERS:
        lo, hi = r.write
        if r.access is not reg.R:
            assert r.type.raw_range[0] <= lo < hi <= r.type.raw_range[1], r.name
        if r.width == 1:
            rlo, rhi = r.read_range
            assert r.type.raw_range[0] <= rlo < rhi <= r.type.raw_range[1], r.name
    assert {r.quantity for r in WRITABLE} == WRITABLE_QUANTITIES
    assert all(r.access in (reg.R, reg.RW_INSTRUCTOR) for r in INPUT_REGISTERS)


# --- round trips at every register's scale -----------------------------------------------------------------

@SLOW
@given(st.data(), pv_ranges, st.booleans())
def test_every_writable_register_round_trips_raw_to_physical_and_back(data, pv_range, reverse):
    """A write's raw word decodes to a physical value that encodes to the same word (what a read returns)."""
    sc = _scaling(pv_range=pv_range, ma_table=REVERSE_MA if reverse else None)
    for r in WRITABLE:
        lo, hi = write_range(r, sc, 0)
        raw = data.draw(st.integers(int(lo), int(hi)), label=r.name)
        value = decode_value(r, raw, sc, 0)
        assert encode_value(r, value, sc, 0) == (raw & 0xFFFF,), r.name
        # and the device's decoder agrees with the table's write
        word = raw & 0xFFFF
        [(quantity, decoded)] = decode_write(r.address, [word], sc, 0, role=INSTRUCTOR)
        assert quantity == r.quantity and (decoded == value or (math.isnan(decoded) and math.isnan(value)))


@SLOW
@given(st.data(), pv_ranges)
def test_every_scaled_register_reads_within_half_a_step(data, pv_range):
    """physical -> raw -> physical loses at most half of one raw step, at the register's own scale."""
    sc = _scaling(pv_range=pv_range)
    for r in SIXTEEN:
        # flags and bits are exact; op_ma decodes within the loop's op_limits (its round trip is tested above)
        if r.conversion in (Conversion.FLAG, Conversion.BITS, Conversion.LOOP_CURRENT):
            continue
        rlo, rhi = r.read_range
        lo_phys, hi_phys = sorted((decode_value(r, rlo, sc, 0), decode_value(r, rhi, sc, 0)))
        x = data.draw(st.floats(lo_phys, hi_phys), label=r.name)
        [word] = encode_value(r, x, sc, 0)
        raw = word - 0x10000 if r.type is DataType.INT16 and word >= 0x8000 else word
        step = abs(decode_value(r, rlo + 1, sc, 0) - decode_value(r, rlo, sc, 0))
        assert abs(decode_value(r, raw, sc, 0) - x) <= 0.5 * step * (1 + 1e-9), r.name


@given(st.floats(allow_nan=False, allow_infinity=False, width=32), st.integers(0, 2**40))
def test_both_word_orders_for_every_32_bit_register(x, count):
    for r in THIRTY_TWO:
        value = count if r.conversion is Conversion.COUNTER else x
        abcd = encode_value(r, value, _scaling(word_order="ABCD"), 0)
        cdab = encode_value(r, value, _scaling(word_order="CDAB"), 0)
        assert cdab == abcd[::-1], r.name
        expected = count % 2**32 if r.conversion is Conversion.COUNTER else x
        assert from_words(abcd, r.type, "ABCD") == expected == from_words(cdab, r.type, "CDAB"), r.name
        point = _modbus.parse_point(r.name)   # the clients read it the same way
        assert point.decode(list(cdab), "CDAB") == pytest.approx(expected, rel=1e-7), r.name


@given(st.floats(-300.0, 300.0), st.sampled_from(["ABCD", "CDAB"]))
def test_clients_decode_every_named_register_at_its_scale(x, order):
    sc = _scaling(word_order=order)
    for r in REGISTERS:
        if r.conversion is not Conversion.LINEAR or r.zero_is_off:
            continue
        words = list(encode_value(r, x, sc, 0))
        got = _modbus.parse_point(r.name).decode(words, order)
        if r.type is DataType.FLOAT32:
            assert got == pytest.approx(x, rel=1e-6, abs=1e-30), r.name
        else:   # the raw word over the scale, inside the read range
            rlo, rhi = r.read_range
            assert got == pytest.approx(min(max(round(x * r.scale), rlo), rhi) / r.scale), r.name


# --- the compiled pass equals the plain-Python codec ----------------------------------------------------

finite = st.floats(-1e4, 1e4, allow_nan=False)
oddities = st.sampled_from([math.nan, math.inf, -math.inf, 1e12, -1e12, 0.0, 100.0, 327.675])
value = st.one_of(finite, oddities)


@st.composite
def states(draw):
    n = draw(st.integers(1, 6))
    floats = {name: draw(st.lists(value, min_size=n, max_size=n))
              for name in ("op", "mv", "flow", "pv", "sp", "kc", "ti", "td", "S", "J", "load", "noise_std")}
    bools = {name: draw(st.lists(st.booleans(), min_size=n, max_size=n))
             for name in ("stuck", "sat_low", "sat_high", "has_controller", "auto", "frozen")}
    state = SimpleNamespace(**{k: np.asarray(v, dtype=float) for k, v in floats.items()},
                            **{k: np.asarray(v, dtype=bool) for k, v in bools.items()})
    ranges = [draw(pv_ranges) for _ in range(n)]
    tables = [draw(st.sampled_from([None, REVERSE_MA])) for _ in range(n)]
    parts = [Scaling.build(1, pv_range=rg, has_controller=c, ma_table=t)
             for rg, c, t in zip(ranges, state.has_controller, tables)]
    sc = Scaling(np.array([p.pv_lo[0] for p in parts]), np.array([p.pv_hi[0] for p in parts]),
                 state.has_controller, tuple(p.tables[0] for p in parts), draw(st.sampled_from(["ABCD", "CDAB"])))
    counters = dict(tick=draw(st.integers(0, 2**33)), overruns=draw(st.integers(0, 2**33)),
                    time=draw(st.one_of(finite, oddities)))
    return state, sc, counters


@SLOW
@given(states())
def test_compiled_encoder_equals_the_plain_python_codec(case):
    state, sc, counters = case
    words = encode(state, sc, **counters)
    for i in range(sc.n):
        assert list(words[i]) == list(encode_loop(state, sc, i, **counters)), i


def test_a_state_of_lists_or_read_only_arrays_reaches_the_encoder_as_the_same_argument_types():
    """numba compiles a kernel once per argument type and a read-only array is a type of its own: whatever form
    the state's values take (arrays, read-only arrays, lists, scalars), the plain encoder gets writable contiguous
    arrays of the same numbers, so it is compiled once (a second encoder took about 10 s on a fresh cache)."""
    import numba

    from valve_emulator.device.registers.kernel import _INPUTS, _inputs

    arrays = {name: (np.arange(3) % 2).astype(dtype) for name, dtype, _ in _INPUTS}
    frozen = {name: a.copy() for name, a in arrays.items()}
    for a in frozen.values():
        a.flags.writeable = False
    lists = {name: a.tolist() for name, a in arrays.items()}
    want = _inputs(SimpleNamespace(**arrays), 3)
    for form in (frozen, lists):
        got = _inputs(SimpleNamespace(**form), 3)
        assert [numba.typeof(a) for a in got] == [numba.typeof(a) for a in want]
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
    scalars = _inputs(SimpleNamespace(**{name: a[1] for name, a in arrays.items()}), 3)
    assert [numba.typeof(a) for a in scalars] == [numba.typeof(a) for a in want]


def test_optional_fault_arrays_read_zero_in_both_encoders():
    state = SimpleNamespace(op=[10.0], mv=[9.0], flow=[9.0], pv=[1.0], sp=[2.0], kc=[1.0], ti=[5.0], td=[0.0],
                            S=[1.0], J=[0.5], stuck=[False], sat_low=[False], sat_high=[False],
                            has_controller=[True], auto=[True])
    sc = _scaling()
    row = encode(state, sc, tick=1, overruns=0, time=0.1)[0]
    assert list(row) == list(encode_loop(state, sc, 0, tick=1, overruns=0, time=0.1))
    assert row[reg.address_of("load")] == row[reg.address_of("noise")] == row[reg.address_of("fault")] == 0


# --- patch equals a full re-encode --------------------------------------------------------------------

_STATE_OF = {"noise": "noise_std", "fault": "frozen"}   # quantity -> the state array that carries it
writes = st.one_of(
    st.tuples(st.just("op"), st.floats(0.0, 100.0)),
    st.tuples(st.just("sp"), finite),
    st.tuples(st.just("auto"), st.booleans()),
    st.tuples(st.just("kc"), st.floats(0.001, 65.0)),
    st.tuples(st.just("ti"), st.one_of(st.floats(0.1, 6000.0), st.just(math.inf))),
    st.tuples(st.just("td"), st.floats(0.0, 6000.0)),
    st.tuples(st.sampled_from(["S", "J"]), st.floats(0.0, 100.0)),
    st.tuples(st.just("load"), st.floats(-100.0, 100.0)),
    st.tuples(st.just("noise"), st.floats(0.0, 1e3)),
    st.tuples(st.just("fault"), st.integers(0, 1)),
)


@SLOW
@given(states(), st.lists(writes, min_size=1, max_size=6))
def test_patch_equals_a_full_re_encode(case, changes):
    state, sc, counters = case
    state.has_controller[:] = True          # a controller's quantities are written only where there is one
    sc = dataclasses.replace(sc, has_controller=state.has_controller)
    words = encode(state, sc, **counters)
    for i in range(sc.n):
        row = words[i].copy()
        for quantity, v in changes:
            patch(row, quantity, v, sc, i)
            name = _STATE_OF.get(quantity, quantity)
            getattr(state, name)[i] = bool(v & 1) if quantity == "fault" else v
        assert list(row) == list(encode(state, sc, **counters)[i]), (i, changes)


def test_patch_refuses_a_quantity_nobody_writes():
    with pytest.raises(KeyError, match="'mv' is not writable"):
        patch(np.zeros(reg.N_REGISTERS, dtype=np.int64), "mv", 1.0, _scaling(), 0)


def test_register_errors_carry_their_data():
    sc = _scaling()
    with pytest.raises(reg.RegisterValueError) as info:
        decode_write(reg.address_of("kc"), [0], sc, 0)
    assert (info.value.register, info.value.value, info.value.allowed) == ("kc", 0, (1, 65535))
    with pytest.raises(reg.RegisterAccessError) as info:
        decode_write(reg.address_of("S"), [1], sc, 0)
    assert info.value.register == "S"
    with pytest.raises(reg.RegisterAddressError) as info:
        reg.check_read("holding", 30, 5)
    assert (info.value.address, info.value.count) == (30, 5)
