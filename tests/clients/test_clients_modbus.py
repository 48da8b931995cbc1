"""Register specs: parsing, encode/decode round trips in both word orders, grouped reads and their fallback."""

from __future__ import annotations

import argparse
import asyncio
import struct
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from valve_emulator.clients._channels import add_channel_arguments, channels_from_args, emulator_channels
from valve_emulator.clients._modbus import DeviceError, Link, Point, Reader, parse_point
from valve_emulator.clients._schedule import next_or_retry
from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import address_of
from valve_emulator.device.server import EmulatorServer
from valve_emulator.errors import UserError

pytestmark = pytest.mark.usefixtures("no_task_leak")


def test_parse_register_names_and_addresses():
    assert parse_point("pv_f32") == Point("holding", 24, "float32", 1.0, 0.0, None, "pv_f32")
    assert parse_point("op_pct").scale == 100.0 and parse_point("load").type == "int16"
    p = parse_point("ir:0x10:int32:2.5:-3")
    assert (p.table, p.address, p.type, p.scale, p.offset, p.width) == ("input", 16, "int32", 2.5, -3.0, 2)
    assert parse_point("holding:12:bit5").bit == 5
    assert parse_point("input:7") == Point("input", 7, "uint16", 1.0, 0.0, None, "input:7")


@pytest.mark.parametrize("text, message", [
    ("coils:3", "neither a register"), ("holding", "neither a register"), ("holding:x", "not an integer"),
    ("holding:70000", "outside 0..65535"), ("holding:1:float16", "type 'float16'"),
    ("holding:1:uint16:0", "nonzero"), ("holding:1:bit16", "bit0..bit15"), ("hr:65535:float32", "past address"),
])
def test_bad_specs_name_the_flag(text, message):
    with pytest.raises(UserError, match=rf"--thing: .*{message}"):
        parse_point(text, what="--thing")


@given(st.floats(-1e6, 1e6, allow_nan=False), st.sampled_from(["ABCD", "CDAB"]))
def test_float32_round_trips_in_both_word_orders(x, order):
    p = parse_point("holding:0:float32")
    words = p.encode(x, order)
    assert p.decode(words, order) == pytest.approx(x, rel=1e-6, abs=1e-30)
    abcd = p.encode(x, "ABCD")
    assert words == (abcd if order == "ABCD" else abcd[::-1])
    assert struct.unpack(">f", struct.pack(">2H", *abcd))[0] == pytest.approx(x, rel=1e-6)


def test_decoded_float32_is_the_decimal_it_stands_for():
    p = parse_point("holding:0:float32")
    assert p.decode(p.encode(12.3)) == 12.3          # not 12.300000190734863


@given(st.integers(-32768, 32767))
def test_scaled_int16_round_trips(raw):
    p = parse_point("holding:4:int16:500:5000")        # PV as % of a -10..10 range
    value = (raw - 5000) / 500
    assert p.encode(value) == [raw & 0xFFFF] and p.decode([raw & 0xFFFF]) == value


def test_encode_refuses_what_the_type_cannot_hold():
    with pytest.raises(UserError, match="outside uint16"):
        parse_point("op_pct").encode(700.0)
    with pytest.raises(UserError, match="only holding registers"):
        parse_point("input:2").encode(1.0)


def test_channels_from_flags():
    p = argparse.ArgumentParser()
    add_channel_arguments(p)
    ch = channels_from_args(p.parse_args(["--sp", "2.5", "--mv", "none", "--extra", "valve=hr:2:uint16:100",
                                          "--no-extras"]))
    assert ch.sp == 2.5 and ch.mv is None and list(ch.extras) == ["valve"] and ch.status is None
    assert set(emulator_channels().points()) >= {"t", "sp", "op", "mv", "pv", "status", "extra:stuck"}
    with pytest.raises(UserError, match="--extra: 'op' is a standard column"):
        channels_from_args(p.parse_args(["--extra", "op=hr:0"]))


async def test_emulator_channels_are_one_request_and_a_gap_refusal_falls_back():
    cfg = server_from_mapping({"device": {"tick": 0.1}, "loops": [
        {"unit": 1, "plant": {"num": [1.0], "den": [1.0, 1.0]}}]})
    async with EmulatorServer(cfg, time_scale=0) as srv:
        link = Link("127.0.0.1", srv.port, 1)
        await link.connect()
        try:
            reader = emulator_channels().reader(word_order="ABCD")
            [req] = reader.requests                       # one snapshot of the whole map per sample
            assert req.table == "holding" and req.address + req.count == address_of("alarms")
            sample = await reader.read(link)
            assert sample["op"] == 50.0 and sample["extra:stuck"] == 1.0
            before = srv.requests
            # mv_pct (2) and S (10) are input registers; 5..9 between them are not: one merged request is
            # refused, and the reader falls back to one request per run of adjacent points.
            mixed = Reader({"mv": parse_point("input:2:uint16:100"), "S": parse_point("input:10:uint16:100")})
            assert len(mixed.requests) == 1
            assert await mixed.read(link) == {"mv": pytest.approx(sample["mv"], abs=0.01), "S": 0.0}
            assert mixed.max_gap == 0 and len(mixed.requests) == 2 and srv.requests - before == 3
        finally:
            link.close()


async def test_a_failed_poll_is_told_waited_out_and_skipped_and_a_good_one_passes():
    # clients._schedule.next_or_retry, the poll of the recorder and the PLC: a read that fails with a transport or
    # Modbus error is given to `failed`, then `retry` wall seconds go by before the next poll; other errors are bugs.
    class Once:
        def __init__(self, outcome):
            self.outcome = outcome

        async def next(self, read, stop):
            if isinstance(self.outcome, Exception):
                raise self.outcome
            return await read()

    async def read():
        return {"pv": 1.5}

    told = []
    assert await next_or_retry(Once(None), read, None, retry=5.0, failed=told.append) == {"pv": 1.5}
    assert told == []
    for exc in (ConnectionError("gone"), DeviceError("read pv", 2)):
        t0 = time.monotonic()
        assert await next_or_retry(Once(exc), read, None, retry=0.2, failed=told.append) is None
        assert time.monotonic() - t0 >= 0.2 and told[-1] is exc
    stop = asyncio.Event()
    stop.set()   # a stop cuts the wait short
    t0 = time.monotonic()
    assert await next_or_retry(Once(ConnectionError("gone")), read, stop, retry=30.0, failed=told.append) is None
    assert time.monotonic() - t0 < 10.0 and len(told) == 3
    with pytest.raises(ValueError):
        await next_or_retry(Once(ValueError("a bug")), read, None, retry=0.0, failed=told.append)
