"""Modbus/TCP Security roles from the permission table: viewer, operator, instructor, a custom role of
``device.roles``, and certificates whose role is not in the table (no session). Clients: pymodbus' TLS
client, a raw TLS socket, ``openssl s_client``."""

import asyncio
import logging
import ssl
import subprocess
import threading

import pytest
from pymodbus.client import AsyncModbusTlsClient
from required import tool

from valve_emulator.config import server_from_mapping
from valve_emulator.device.certs import modbus_certificate
from valve_emulator.device.registers import address_of
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.tls import server_context

from .conftest import DEVICE

LOGGER = "valve_emulator.device.server"
ROLES = ("viewer", "operator", "instructor", "tuner")


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki-roles")
    modbus_certificate(d, "server", server=True)
    for role in (*ROLES, "readonly"):
        modbus_certificate(d, f"client-{role}", role=role)
    modbus_certificate(d, "client-none")
    return d


@pytest.fixture
def roles_config():
    return server_from_mapping({**DEVICE, "device": {"tick": 0.1, "roles": {"tuner": ["kc", "ti", "td"]}}})


@pytest.fixture
async def tls_server(roles_config, pki):
    async with EmulatorServer(roles_config, port=0, time_scale=0) as srv:
        await srv.open_tls(server_context(pki / "server.pem", pki / "server-key.pem", pki / "ca.pem"), port=0)
        yield srv


def _context(pki, name):
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(pki / "ca.pem"))
    ctx.load_cert_chain(str(pki / f"{name}.pem"), str(pki / f"{name}-key.pem"))
    return ctx


#: (unit, register, raw word, what the bank shows afterwards): one write of each kind
WRITES = {
    "op": (2, "op_pct", 4200, lambda bank: float(bank.op[1]) == pytest.approx(42.0)),
    "sp": (1, "sp", 6000, lambda bank: float(bank.sp[0]) == pytest.approx(30.0)),
    "kc": (1, "kc", 500, lambda bank: float(bank.kc[0]) == pytest.approx(0.5)),
    "S": (1, "S", 150, lambda bank: float(bank.S[0]) == pytest.approx(1.5)),
}
ALLOWED = {"viewer": set(), "operator": {"op", "sp"}, "instructor": {"op", "sp", "kc", "S"}, "tuner": {"kc"}}


@pytest.mark.parametrize("role", ROLES)
async def test_each_role_writes_exactly_its_tags_and_reads_everything(tls_server, pki, role):
    srv = tls_server
    async with AsyncModbusTlsClient("127.0.0.1", port=srv.tls_port, sslctx=_context(pki, f"client-{role}"),
                                    retries=0) as client:
        rr = await client.read_holding_registers(0, count=31, device_id=1)
        assert not rr.isError() and len(rr.registers) == 31
        for tag, (unit, register, word, _) in WRITES.items():
            wr = await client.write_register(address_of(register), word, device_id=unit)
            assert wr.isError() == (tag not in ALLOWED[role]), (role, tag)
            if wr.isError():
                assert wr.exception_code == 2
    srv.device.advance(1)
    for tag, (*_, shows) in WRITES.items():
        assert shows(srv.device.bank) == (tag in ALLOWED[role]), (role, tag)


async def test_a_refused_write_is_logged_with_address_certificate_and_role(tls_server, pki, caplog):
    caplog.set_level(logging.WARNING, logger=LOGGER)
    async with AsyncModbusTlsClient("127.0.0.1", port=tls_server.tls_port, sslctx=_context(pki, "client-viewer"),
                                    retries=0) as client:
        assert (await client.write_register(address_of("op_pct"), 1000, device_id=2)).isError()
    [line] = [r.getMessage() for r in caplog.records if "refused write" in r.getMessage()]
    assert "127.0.0.1" in line and "CN=client-viewer" in line and "role 'viewer'" in line


async def test_a_flood_of_refused_writes_writes_one_log_line_per_interval(tls_server, pki, caplog):
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    async with AsyncModbusTlsClient("127.0.0.1", port=tls_server.tls_port, sslctx=_context(pki, "client-viewer"),
                                    retries=0) as client:
        for _ in range(300):
            assert (await client.write_register(address_of("op_pct"), 1000, device_id=2)).isError()
    lines = [r for r in caplog.records if r.levelno >= logging.WARNING and "refused write" in r.getMessage()]
    assert len(lines) == 1
    assert tls_server.refusals.refused == 300


async def _session_closed(port, ctx):
    """Open a TLS connection, send one read request; True when the server closes without answering."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, ssl=ctx)
    try:
        writer.write(bytes.fromhex("000100000006010300000001"))
        await writer.drain()
        data = await asyncio.wait_for(reader.read(100), 5)
        return data == b""
    except (ConnectionError, ssl.SSLError):
        return True
    finally:
        writer.close()


@pytest.mark.parametrize(("name", "claim"), [("client-readonly", "role 'readonly'"), ("client-none", "no role")])
async def test_a_certificate_whose_role_is_not_in_the_table_gets_no_session(tls_server, pki, caplog, name, claim):
    caplog.set_level(logging.WARNING, logger=LOGGER)
    srv = tls_server
    assert await _session_closed(srv.tls_port, _context(pki, name))
    assert srv.requests == 0 and srv.tls_refused == 1
    [line] = [r.getMessage() for r in caplog.records if "refused TLS session" in r.getMessage()]
    assert "127.0.0.1" in line and f"CN={name}" in line and claim in line
    assert "viewer, operator, instructor, tuner" in line


async def test_repeated_refused_handshakes_are_logged_once_per_interval(tls_server, pki, caplog):
    caplog.set_level(logging.WARNING, logger=LOGGER)
    for _ in range(20):
        assert await _session_closed(tls_server.tls_port, _context(pki, "client-readonly"))
    assert tls_server.tls_refused == 20
    assert len([r for r in caplog.records if "refused TLS session" in r.getMessage()]) == 1


async def test_without_the_custom_role_in_the_config_its_certificate_gets_no_session(config, pki):
    async with EmulatorServer(config, port=0, time_scale=0) as srv:   # no device.roles: no "tuner"
        await srv.open_tls(server_context(pki / "server.pem", pki / "server-key.pem", pki / "ca.pem"), port=0)
        assert await _session_closed(srv.tls_port, _context(pki, "client-tuner"))
        assert srv.tls_refused == 1


@pytest.fixture
def tls_thread_server(roles_config, pki):
    """The TLS server on its own event loop thread, so that a blocking subprocess can talk to it."""
    started, box = threading.Event(), {}

    async def main():
        box["stop"] = asyncio.Event()
        async with EmulatorServer(roles_config, port=0, time_scale=0) as srv:
            await srv.open_tls(server_context(pki / "server.pem", pki / "server-key.pem", pki / "ca.pem"), port=0)
            box["srv"], box["loop"] = srv, asyncio.get_running_loop()
            started.set()
            await box["stop"].wait()

    thread = threading.Thread(target=asyncio.run, args=(main(),), daemon=True)
    thread.start()
    assert started.wait(30)
    yield box["srv"]
    box["loop"].call_soon_threadsafe(box["stop"].set)
    thread.join(10)


def _s_client(port, pki, name):
    """What ``openssl s_client`` with this certificate receives for a Modbus read (unit 1, holding 0): it stays
    connected while the server does, so it runs at most 5 s."""
    cmd = ["openssl", "s_client", "-connect", f"127.0.0.1:{port}", "-CAfile", str(pki / "ca.pem"), "-tls1_2",
           "-cert", str(pki / f"{name}.pem"), "-key", str(pki / f"{name}-key.pem"), "-quiet"]
    try:
        return subprocess.run(cmd, input=bytes.fromhex("000100000006010300000001"), capture_output=True,
                              timeout=5).stdout
    except subprocess.TimeoutExpired as exc:
        return exc.output or b""


def test_openssl_with_a_known_role_is_answered_and_with_an_unknown_one_is_cut_off(tls_thread_server, pki):
    tool("openssl", "apt-get install openssl")
    srv = tls_thread_server
    answered = _s_client(srv.tls_port, pki, "client-viewer")
    assert answered[:2] == b"\x00\x01" and answered[7:9] == b"\x03\x02", answered   # FC3, 2 bytes
    assert _s_client(srv.tls_port, pki, "client-readonly") == b""
    assert srv.tls_sessions == 2 and srv.tls_refused == 1 and srv.requests == 1


async def _handshake_refused(port, ctx):
    """Try a TLS session with ``ctx``; True when the server refuses it (in the handshake or at the first read)."""
    try:
        return await _session_closed(port, ctx)
    except (ssl.SSLError, ConnectionError, asyncio.IncompleteReadError):
        return True


@pytest.mark.parametrize(("client", "reason"), [
    (None, "PEER_DID_NOT_RETURN_A_CERTIFICATE"),
    ("foreign", "certificate verify failed"),
])
async def test_a_failed_handshake_is_logged_with_the_address_and_the_reason(tls_server, pki, tmp_path, caplog,
                                                                             client, reason):
    caplog.set_level(logging.WARNING, logger=LOGGER)
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(pki / "ca.pem"))
    if client == "foreign":   # a certificate of another CA
        modbus_certificate(tmp_path, "client-operator", role="operator")
        ctx.load_cert_chain(str(tmp_path / "client-operator.pem"), str(tmp_path / "client-operator-key.pem"))
    for _ in range(10):
        assert await _handshake_refused(tls_server.tls_port, ctx)
    assert tls_server.tls_failed == 10 and tls_server.tls_sessions == 0 and tls_server.requests == 0
    [line] = [r.getMessage() for r in caplog.records if "refused TLS handshake" in r.getMessage()]
    assert "from 127.0.0.1" in line and reason in line
