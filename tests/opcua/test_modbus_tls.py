"""Modbus/TCP Security: TLS 1.2+ with client certificates; the certificate's role decides instructor writes.
Clients: pymodbus' TLS client and ``openssl s_client`` (Debian's openssl). The other roles: test_tls_roles.py."""

import asyncio
import ssl
import subprocess

import pytest
from pymodbus.client import AsyncModbusTlsClient
from required import tool

from valve_emulator.device.certs import modbus_certificate
from valve_emulator.device.registers import address_of
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.tls import role_of, server_context


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    """A test CA, the server's certificate and one client certificate per role (and one without a role)."""
    d = tmp_path_factory.mktemp("pki")
    modbus_certificate(d, "server", server=True)
    for role in ("operator", "instructor"):
        modbus_certificate(d, f"client-{role}", role=role)
    modbus_certificate(d, "client-none")
    return d


@pytest.fixture
async def tls_server(config, pki):
    async with EmulatorServer(config, port=0, time_scale=0) as srv:
        await srv.open_tls(server_context(pki / "server.pem", pki / "server-key.pem", pki / "ca.pem"), port=0)
        yield srv


def _client_context(pki, name):
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(pki / "ca.pem"))
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    if name is not None:
        ctx.load_cert_chain(str(pki / f"{name}.pem"), str(pki / f"{name}-key.pem"))
    return ctx


def test_the_role_extension_round_trips(pki):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    def der(name):
        cert = x509.load_pem_x509_certificate((pki / f"{name}.pem").read_bytes())
        return cert.public_bytes(serialization.Encoding.DER)

    assert role_of(der("client-instructor")) == "instructor"
    assert role_of(der("client-operator")) == "operator"
    assert role_of(der("client-none")) is None
    assert role_of(None) is None


@pytest.mark.parametrize(("name", "allowed"), [("client-instructor", True), ("client-operator", False)])
async def test_instructor_writes_only_from_an_instructor_certificate(tls_server, pki, name, allowed):
    srv = tls_server
    async with AsyncModbusTlsClient("127.0.0.1", port=srv.tls_port, sslctx=_client_context(pki, name),
                                    retries=0) as client:
        assert client.connected
        rr = await client.read_holding_registers(0, count=31, device_id=1)      # everyone reads
        assert not rr.isError() and len(rr.registers) == 31
        wr = await client.write_register(address_of("S"), 150, device_id=1)     # S = 1.5 %: instructor only
        assert wr.isError() != allowed
        if not allowed:
            assert wr.exception_code == 2
        wr = await client.write_register(address_of("op_pct"), 4200, device_id=2)   # OP: both roles
        assert not wr.isError()
    srv.device.advance(1)
    assert float(srv.device.bank.S[0]) == (1.5 if allowed else 5.0)
    assert float(srv.device.bank.op[1]) == pytest.approx(42.0)


async def test_no_client_certificate_no_session(tls_server, pki):
    srv = tls_server
    ctx = _client_context(pki, None)
    with pytest.raises((ssl.SSLError, ConnectionError, asyncio.IncompleteReadError)):
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.tls_port, ssl=ctx)
        # TLS 1.3 reports the missing certificate at the first read
        writer.write(bytes.fromhex("000100000006010300000001"))
        await writer.drain()
        await asyncio.wait_for(reader.readexactly(1), 5)
    assert srv.requests == 0


def _s_client(port, pki, *args):
    cmd = ["openssl", "s_client", "-connect", f"127.0.0.1:{port}", "-CAfile", str(pki / "ca.pem"), *args]
    return subprocess.run(cmd, input=b"", capture_output=True, timeout=30)


@pytest.fixture
async def tls_thread_server(config, pki):
    """The TLS server on its own event loop thread, so that a blocking subprocess can talk to it."""
    import threading

    started, stop = threading.Event(), None
    box = {}

    async def main():
        nonlocal stop
        stop = asyncio.Event()
        async with EmulatorServer(config, port=0, time_scale=0) as srv:
            await srv.open_tls(server_context(pki / "server.pem", pki / "server-key.pem", pki / "ca.pem"), port=0)
            box["srv"], box["loop"] = srv, asyncio.get_running_loop()
            started.set()
            await stop.wait()

    thread = threading.Thread(target=asyncio.run, args=(main(),), daemon=True)
    thread.start()
    assert started.wait(30)
    yield box["srv"]
    box["loop"].call_soon_threadsafe(stop.set)
    thread.join(10)


def test_openssl_gets_a_session_only_with_a_certificate_and_tls_1_2_or_later(tls_thread_server, pki):
    tool("openssl", "apt-get install openssl")
    srv = tls_thread_server
    port = srv.tls_port
    operator = ("-cert", str(pki / "client-operator.pem"), "-key", str(pki / "client-operator-key.pem"))
    good = _s_client(port, pki, "-tls1_2", *operator)
    assert b"Verify return code: 0 (ok)" in good.stdout, good.stdout[-400:]
    assert _wait(lambda: srv.tls_sessions == 1)
    # without a client certificate the server ends the handshake: no session, whatever the TLS version
    for version in ("-tls1_2", "-tls1_3"):
        bare = _s_client(port, pki, version)
        assert bare.returncode != 0 or b"alert" in bare.stderr.lower() or version == "-tls1_3"
    # TLS 1.1 is refused even with a good certificate: no cipher is agreed
    old = _s_client(port, pki, "-tls1_1", *operator)
    assert old.returncode != 0
    assert b"Cipher is (NONE)" in old.stdout or b"alert" in old.stderr.lower()
    assert not _wait(lambda: srv.tls_sessions > 1, timeout=1.0)
    assert srv.tls_sessions == 1


def _wait(condition, timeout=5.0):
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return condition()
