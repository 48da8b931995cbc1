"""Clients that are not ours against ``valve-emulator serve --opcua``: asyncua's command-line tools (uals, uaread,
uawrite) and a Basic256Sha256 Sign&Encrypt session with a user name; the refusal to listen beyond loopback
without security; ``valve-emulator certs``."""

from __future__ import annotations

import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from asyncua import Client, ua

from valve_emulator.cli import main
from valve_emulator.opcua import NAMESPACE, hash_password
from valve_emulator.opcua.server import APPLICATION_URI

OPCUA_LINE = re.compile(r"OPC UA at (opc\.tcp://\S+)")


def start_serve(*args: str) -> tuple[subprocess.Popen, str, int]:
    """``serve --port 0 --time-scale 10 ARGS`` as a user runs it; returns (process, OPC UA URL, Modbus port)."""
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", "--port", "0", "--time-scale", "10",
                             *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url, port = None, None
    for _ in range(6):
        line = proc.stdout.readline()
        if not line:
            break
        if m := re.search(r"listening on [\d.]+:(\d+)", line):
            port = int(m.group(1))
        if m := OPCUA_LINE.search(line):
            url = m.group(1)
            break
    if url is None:
        proc.kill()
        raise AssertionError(f"no OPC UA line: {proc.communicate()[1][-2000:]}")
    return proc, url, port


def stop(proc: subprocess.Popen) -> str:
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return err


@pytest.fixture(scope="module")
def default_served():
    proc, url, port = start_serve("--opcua", "0")
    yield url, port
    err = stop(proc)
    assert "Traceback" not in err, err


def _tool(name: str, *args: str) -> subprocess.CompletedProcess:
    exe = shutil.which(name)
    assert exe, f"{name} (asyncua's command-line client) is required"
    return subprocess.run([exe, *args], capture_output=True, text=True, timeout=60)


def test_uals_browses_the_loop(default_served):
    url, _ = default_served
    out = _tool("uals", "-u", url, "-n", "ns=2;s=Unit1.concentration_undershoot", "-l", "0")
    assert out.returncode == 0, out.stderr[-1000:]
    for name in ("pv", "sp", "op", "mv", "S", "J", "stuck"):
        assert f"Text='{name}')" in out.stdout, (name, out.stdout[:2000])


def test_uawrite_then_uaread_and_modbus_agree(default_served):
    from pymodbus.client import ModbusTcpClient

    url, port = default_served
    node = "ns=2;s=Unit1.concentration_undershoot.op"
    written = _tool("uawrite", "-u", url, "-n", node, "-t", "double", "37.5")
    assert written.returncode == 0, written.stderr[-1000:]
    read = _tool("uaread", "-u", url, "-n", node)
    assert read.returncode == 0 and float(read.stdout.strip()) == pytest.approx(37.5), read.stdout + read.stderr
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=10)
    assert client.connect()
    try:
        assert client.read_holding_registers(0, count=1, device_id=1).registers[0] == 3750
    finally:
        client.close()
    refused = _tool("uawrite", "-u", url, "-n", "ns=2;s=Unit1.concentration_undershoot.S", "-t", "double", "1")
    assert refused.returncode != 0 or "BadUserAccessDenied" in refused.stdout + refused.stderr


def test_serve_refuses_opcua_beyond_loopback_without_security(capsys):
    assert main(["serve", "--host", "0.0.0.0", "--port", "0", "--opcua", "0"]) == 2
    assert "beyond loopback" in capsys.readouterr().err


def test_certs_makes_an_application_certificate_with_the_servers_uri(tmp_path):
    from cryptography import x509

    assert main(["certs", "--opcua", str(tmp_path)]) == 0
    cert = x509.load_der_x509_certificate((tmp_path / "server.der").read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.UniformResourceIdentifier) == [APPLICATION_URI]
    assert (tmp_path / "server-key.pem").stat().st_mode & 0o077 == 0   # the key is private


@pytest.fixture(scope="module")
def secure_files(tmp_path_factory):
    from valve_emulator.device.certs import opcua_certificate

    d = tmp_path_factory.mktemp("opcua")
    assert main(["certs", "--opcua", str(d)]) == 0
    opcua_certificate(d, application_uri="urn:valve-emulator:test-client", name="client")
    trusted = d / "pki" / "trusted" / "certs"   # the client is trusted (docs/opcua.md: the trust list)
    trusted.mkdir(parents=True)
    (trusted / "client.der").write_bytes((d / "client.der").read_bytes())
    users = d / "users.yaml"
    users.write_text(f"users:\n  ines: {{role: instructor, password: '{hash_password('teach', iterations=2000)}'}}\n"
                     f"  otto: {{role: operator, password: '{hash_password('run', iterations=2000)}'}}\n")
    return d


async def test_basic256sha256_sign_and_encrypt_with_users(secure_files):
    d = secure_files
    proc, url, _ = start_serve("--opcua", "0", "--opcua-policy", "Basic256Sha256", "--opcua-cert",
                               str(d / "server.der"), "--opcua-key", str(d / "server-key.pem"),
                               "--opcua-users", str(d / "users.yaml"), "--opcua-pki", str(d / "pki"))
    try:
        security = f"Basic256Sha256,SignAndEncrypt,{d / 'client.der'},{d / 'client-key.pem'},{d / 'server.der'}"
        client = Client(url)
        await client.set_security_string(security)
        client.application_uri = "urn:valve-emulator:test-client"
        client.set_user("ines")
        client.set_password("teach")
        async with client:
            ns = await client.get_namespace_index(NAMESPACE)
            loop = await client.nodes.objects.get_child([f"{ns}:ValveEmulator", f"{ns}:Unit1",
                                                         f"{ns}:concentration_undershoot"])
            S = await loop.get_child(f"{ns}:S")
            await S.write_value(ua.DataValue(ua.Variant(2.5, ua.VariantType.Double)))
            assert await S.read_value() == pytest.approx(2.5)
        # the only endpoint is the secure one: a plain client gets no session
        plain = Client(url)
        with pytest.raises(Exception):  # noqa: B017 - asyncua raises differently per stage; any refusal will do
            async with plain:
                pass
        wrong = Client(url)
        await wrong.set_security_string(security)
        wrong.application_uri = "urn:valve-emulator:test-client"
        wrong.set_user("ines")
        wrong.set_password("nope")
        with pytest.raises(ua.UaStatusCodeError):
            async with wrong:
                pass
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]


def test_users_file_errors_name_file_and_key(tmp_path, capsys):
    bad = tmp_path / "users.yaml"
    bad.write_text("users:\n  ines: {role: boss, password: x}\n")
    assert main(["serve", "--port", "0", "--opcua", "0", "--opcua-users", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "users.ines.role" in err
    bad.write_text("users:\n  ines: {role: instructor, password: plain-text}\n")
    assert main(["serve", "--port", "0", "--opcua", "0", "--opcua-users", str(bad)]) == 2
    assert "users.ines.password" in capsys.readouterr().err
    assert Path(bad).read_text().count("plain-text") == 1   # nothing rewritten


def test_config_sections_serve_opcua_and_tls_with_paths_relative_to_the_file(tmp_path):
    """``opcua:`` and ``tls:`` in a server file do what the flags do; a missing key is named with its line."""
    from pymodbus.client import ModbusTlsClient

    from valve_emulator.config import ConfigError, load_server
    from valve_emulator.device.certs import modbus_certificate

    modbus_certificate(tmp_path / "pki", "server", server=True)
    modbus_certificate(tmp_path / "pki", "client-instructor", role="instructor")
    cfg = tmp_path / "plant.yaml"
    cfg.write_text("device: {tick: 0.1}\nloops:\n  - {unit: 1, name: FIC1, plant: {fopdt: {gain: 1, tau: 5}}}\n"
                   "opcua: {port: 0}\n"
                   "tls: {port: 0, certificate: pki/server.pem, private_key: pki/server-key.pem, ca: pki/ca.pem}\n")
    loaded = load_server(cfg)
    assert loaded.opcua.port == 0 and loaded.tls.ca == str(tmp_path / "pki" / "ca.pem")
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", str(cfg), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline() for _ in range(3)]
        assert any(OPCUA_LINE.search(ln) for ln in lines), lines
        tls = next(re.search(r"Modbus/TCP Security .* on [\d.]+:(\d+)", ln) for ln in lines if "Security" in ln)
        import ssl

        ctx = ssl.create_default_context(cafile=str(tmp_path / "pki" / "ca.pem"))
        ctx.check_hostname = False   # pymodbus' synchronous client passes no server name; the CA is still checked
        ctx.load_cert_chain(str(tmp_path / "pki" / "client-instructor.pem"),
                            str(tmp_path / "pki" / "client-instructor-key.pem"))
        client = ModbusTlsClient("127.0.0.1", port=int(tls.group(1)), sslctx=ctx, retries=0)
        assert client.connect()
        assert not client.write_register(10, 250, device_id=1).isError()   # S: an instructor certificate
        client.close()
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]
    cfg.write_text("device: {tick: 0.1}\nloops:\n  - {unit: 1, plant: {fopdt: {gain: 1, tau: 5}}}\n"
                   "tls:\n  port: 802\n  certificate: a.pem\n")
    with pytest.raises(ConfigError, match=r"plant.yaml:4: tls.private_key is required"):
        load_server(cfg)
