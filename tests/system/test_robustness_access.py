"""Access control: read-only mode refuses with 0x01, instructor gating with 0x02, nothing changes,
every refused write is logged once per client and register, live reconfiguration, the bind warning."""

from __future__ import annotations

import asyncio
import logging
import struct

import pytest

from valve_emulator.config import server_from_mapping
from valve_emulator.device.guard import RefusalLog, binds_all_interfaces
from valve_emulator.device.pdu import malformed, register_names, write_target
from valve_emulator.device.registers import N_REGISTERS, address_of
from valve_emulator.device.runtime import apply_overrides
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

OPEN_LOOP, WITH_PI = 1, 2
LOGGER = "valve_emulator.device.server"


def _config(**device):
    return server_from_mapping({"device": {"tick": 0.1, **device}, "loops": [
        {"unit": OPEN_LOOP, "plant": {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]}},
        {"unit": WITH_PI, "plant": {"num": [1.0], "den": [1.0, 0.0], "pv_range": [-10.0, 10.0]},
         "controller": {"kc": 0.4, "ti": 2.0, "mode": "manual"}},
    ]})


@pytest.fixture
def make_server(fake_bank_cls):
    def make(config):
        return EmulatorServer(config, bank=fake_bank_cls.for_config(config), time_scale=0)
    return make


class Raw:
    """A raw Modbus TCP client: one request, one answer ``(function code byte, rest of the PDU)``."""

    def __init__(self, reader, writer):
        self.reader, self.writer, self.tid = reader, writer, 0

    @classmethod
    async def connect(cls, port):
        return cls(*await asyncio.open_connection("127.0.0.1", port))

    async def ask(self, unit, pdu):
        self.tid += 1
        self.writer.write(struct.pack(">HHHB", self.tid, 0, len(pdu) + 1, unit) + pdu)
        header = await asyncio.wait_for(self.reader.readexactly(7), 2)
        body = await self.reader.readexactly(struct.unpack(">H", header[4:6])[0] - 1)
        assert struct.unpack(">H", header[:2])[0] == self.tid
        return body[0], body[1:]

    async def close(self):
        self.writer.close()
        await self.writer.wait_closed()


WRITES = {
    "fc6 op": lambda unit: struct.pack(">BHH", 6, address_of("op_pct"), 2500),
    "fc6 S": lambda unit: struct.pack(">BHH", 6, address_of("S"), 300),
    "fc16 op": lambda unit: struct.pack(">BHHBHH", 16, 0, 2, 4, 2500, 8000),
    "fc16 S,J": lambda unit: struct.pack(">BHHBHH", 16, address_of("S"), 2, 4, 300, 100),
    "fc23": lambda unit: struct.pack(">BHHHHBH", 23, 0, 2, 0, 1, 2, 2500),
    "fc6 fault": lambda unit: struct.pack(">BHH", 6, address_of("fault"), 1),
}


def _state(srv):
    return bytes(srv.device.image), dict(srv.device._pending), list(srv.device.bank.calls)


@pytest.mark.parametrize("name", list(WRITES))
async def test_read_only_refuses_every_write_with_0x01_and_changes_nothing(make_server, name):
    async with make_server(_config(read_only=True, instructor_writes=True)) as srv:
        client = await Raw.connect(srv.port)
        for unit in (OPEN_LOOP, WITH_PI):
            before = _state(srv)
            fc = WRITES[name](unit)[0]
            assert await client.ask(unit, WRITES[name](unit)) == (fc | 0x80, b"\x01")
            assert _state(srv) == before
        srv.device.advance(1)
        assert srv.device.bank.calls == []
        # reads still work
        fc, body = await client.ask(OPEN_LOOP, struct.pack(">BHH", 3, 0, 2))
        assert fc == 3 and body == b"\x04" + bytes(srv.device.image[:4])
        await client.close()


@pytest.mark.parametrize("device, allowed", [
    ({}, False),                                                           # instructor_writes off
    ({"instructor_writes": True, "instructor_hosts": ["10.1.2.3"]}, False),  # not from a listed host
    ({"instructor_writes": True, "instructor_hosts": ["::ffff:127.0.0.1"]}, True),
    ({"instructor_writes": True}, True),
])
async def test_instructor_registers_are_gated_with_0x02(make_server, device, allowed):
    async with make_server(_config(**device)) as srv:
        client = await Raw.connect(srv.port)
        for name in ("S", "J", "load", "noise", "fault"):
            before = _state(srv)
            pdu = struct.pack(">BHH", 6, address_of(name), 1)
            answer = await client.ask(OPEN_LOOP, pdu)
            if allowed:
                assert answer == (6, pdu[1:])
            else:
                assert answer == (0x86, b"\x02") and _state(srv) == before
        # a multi-register write that touches one instructor register changes nothing at all
        before = _state(srv)
        answer = await client.ask(OPEN_LOOP, struct.pack(">BHHBHH", 16, address_of("td"), 2, 4, 0, 100))
        if not allowed:
            assert answer == (0x90, b"\x02") and _state(srv) == before
        await client.close()


async def test_refused_writes_are_logged_once_per_client_and_register(make_server, caplog):
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    async with make_server(_config()) as srv:
        client = await Raw.connect(srv.port)
        for _ in range(5):
            await client.ask(OPEN_LOOP, struct.pack(">BHH", 6, address_of("S"), 300))
            await client.ask(WITH_PI, struct.pack(">BHH", 6, address_of("J"), 300))
            await client.ask(OPEN_LOOP, struct.pack(">BHH", 6, address_of("mv_pct"), 1))
            await client.ask(OPEN_LOOP, struct.pack(">BHH", 6, 1000 + _, 1))       # outside: one key for all
        await client.close()
        client = await Raw.connect(srv.port)                                      # same client, new connection
        await client.ask(OPEN_LOOP, struct.pack(">BHH", 6, address_of("S"), 300))
        await client.close()
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 4, warnings
    s_line = next(w for w in warnings if "register S " in w)
    assert "refused write from 127.0.0.1" in s_line and "0x02" in s_line and "role 'unauthenticated'" in s_line
    assert any("mv_pct" in w and "read-only" in w for w in warnings)
    assert any("outside the map" in w for w in warnings)
    assert srv.refusals.refused == 21


def test_refusal_log_is_bounded(caplog):
    caplog.set_level(logging.DEBUG)
    log = RefusalLog(logging.getLogger("test.refusals"), capacity=3)
    for i in range(10):
        log.note(f"10.0.0.{i}", ("S", 2), "refused %s", i)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 4 and "holds 3" in warnings[-1]
    assert log.refused == 10


async def test_reconfigure_applies_access_settings_to_open_connections(make_server):
    async with make_server(_config()) as srv:
        client = await Raw.connect(srv.port)
        s_write = struct.pack(">BHH", 6, address_of("S"), 300)
        assert await client.ask(OPEN_LOOP, s_write) == (0x86, b"\x02")
        assert srv.reconfigure(_config(instructor_writes=True)) == []
        assert await client.ask(OPEN_LOOP, s_write) == (6, s_write[1:])          # same connection, new rights
        restart = srv.reconfigure(_config(read_only=True, tick=0.2, max_connections=5, idle_timeout=9.0))
        assert restart == ["device.tick"] and srv.config.device.tick == 0.1
        assert (srv.guard.max_connections, srv.guard.idle_timeout) == (5, 9.0)
        assert await client.ask(OPEN_LOOP, s_write) == (0x86, b"\x01")
        await client.close()


async def test_malformed_writes_are_answered_0x03_before_access_checks(make_server):
    """Spec order: function code (0x01), then quantity/structure (0x03), then address (0x02)."""
    async with make_server(_config(read_only=True)) as srv:
        client = await Raw.connect(srv.port)
        assert await client.ask(OPEN_LOOP, struct.pack(">BHHB", 16, 0, 0, 0)) == (0x90, b"\x03")
        assert await client.ask(OPEN_LOOP, struct.pack(">BHHB", 16, 0, 124, 248) + bytes(240)) == (0x90, b"\x03")
        assert await client.ask(OPEN_LOOP, struct.pack(">BHHHHB", 23, 0, 126, 0, 1, 2) + b"\0\0") == (0x97, b"\x03")
        assert await client.ask(OPEN_LOOP, b"\x07") == (0x87, b"\x01")
        assert await client.ask(OPEN_LOOP, struct.pack(">BHH", 3, 0, N_REGISTERS + 1)) == (0x83, b"\x02")
        await client.close()


@pytest.mark.parametrize("fc, pdu, problem", [
    (3, struct.pack(">BHH", 3, 0, 125), None),
    (3, struct.pack(">BHH", 3, 0, 126), "read count 126"),
    (4, struct.pack(">BHH", 4, 0, 0), "read count 0"),
    (3, struct.pack(">BHHB", 3, 0, 1, 0), "5-byte PDU"),
    (6, b"\x06\x00\x01", "5-byte PDU"),
    (16, struct.pack(">BHHBHH", 16, 0, 2, 4, 1, 2), None),
    (16, struct.pack(">BHHBH", 16, 0, 2, 4, 1), "disagree"),
    (16, struct.pack(">BHHBHH", 16, 0, 2, 3, 1, 2), "disagree"),
    (16, struct.pack(">BHH", 16, 0, 1), "at least 6"),
    (23, struct.pack(">BHHHHBH", 23, 0, 125, 0, 1, 2, 7), None),
    (23, struct.pack(">BHHHHBH", 23, 0, 0, 0, 1, 2, 7), "read count 0"),
    (23, struct.pack(">BHHHHB", 23, 0, 1, 0, 122, 244) + bytes(244), "disagree"),
])
def test_pdu_structure(fc, pdu, problem):
    got = malformed(fc, pdu)
    assert (got is None) if problem is None else (problem in got)


def test_write_targets_and_register_names():
    assert write_target(6, struct.pack(">BHH", 6, 10, 5)) == (10, 1)
    assert write_target(16, struct.pack(">BHHB", 16, 3, 4, 8)) == (3, 4)
    assert write_target(23, struct.pack(">BHHHHB", 23, 0, 1, 28, 3, 6)) == (28, 3)
    assert register_names(13, 4) == ["map_version", "tick", "overruns"]
    assert register_names(N_REGISTERS, 5) == []


@pytest.mark.parametrize("host, everywhere", [("127.0.0.1", False), ("::1", False), ("0.0.0.0", True),
                                              ("::", True), ("", True), ("localhost", False)])
def test_binds_all_interfaces(host, everywhere):
    assert binds_all_interfaces(host) is everywhere


def test_server_binds_loopback_by_default_and_overrides_reach_every_device_section(fake_bank_cls):
    cfg = _config()
    assert EmulatorServer(cfg, bank=fake_bank_cls.for_config(cfg), time_scale=0).host == "127.0.0.1"
    forced = apply_overrides(cfg, read_only=True, max_connections=3)
    assert forced.device.read_only and forced.device.max_connections == 3
    assert all(lp.device.read_only and lp.device.max_connections == 3 for lp in forced.loops)
    assert apply_overrides(cfg) is cfg
