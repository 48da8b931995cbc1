"""`valve-emulator serve` at start-up: the "listening" line only once every requested port is open, and a port
that is taken is one error line naming the flag and the port, exit status 2, nothing on stdout, nothing recorded."""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from valve_emulator.device.certs import modbus_certificate


def _serve(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "valve_emulator", "serve", *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture
def taken_port():
    """A port of 127.0.0.1 that another program listens on for the duration of the test."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield sock.getsockname()[1]


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("pki")
    modbus_certificate(d, "server", server=True)
    return d


def _tls_flags(pki: Path) -> list[str]:
    return ["--tls-cert", str(pki / "server.pem"), "--tls-key", str(pki / "server-key.pem"),
            "--tls-ca", str(pki / "ca.pem")]


@pytest.mark.parametrize("interface", ["--port", "--opcua", "--web", "--tls-port"])
def test_a_taken_port_is_one_line_naming_the_flag_and_nothing_is_written(interface, taken_port, pki, tmp_path):
    """Each interface is asked for with the taken port while every other one gets a free port: the taken one is
    named in a single line, no "listening" line was printed, and neither the recording nor the station's
    snapshot folder was created."""
    ports = {"--port": "0", "--opcua": "0", "--web": "0", "--tls-port": "0", interface: str(taken_port)}
    record, snapshots = tmp_path / "rec.csv", tmp_path / "snapshots"
    flags = [f for flag, port in ports.items() for f in (flag, port)]
    out = _serve(*flags, *_tls_flags(pki), "--record", str(record), "--snapshots", str(snapshots))
    assert out.returncode == 2, out.stderr
    assert out.stdout == ""
    assert out.stderr.splitlines() == [f"valve-emulator serve: error: {interface} {taken_port}: address already "
                                       f"in use"]
    assert not record.exists() and not snapshots.exists()


def test_a_serial_device_that_cannot_be_opened_names_the_rtu_flag(tmp_path):
    missing = tmp_path / "ttyUSB9"
    out = _serve("--port", "0", "--rtu", str(missing))
    assert (out.returncode, out.stdout) == (2, "")
    assert out.stderr.splitlines() == [f"valve-emulator serve: error: --rtu {missing}: no such file or directory"]


def test_listening_comes_first_once_every_port_is_open_then_each_interface_announces_itself(pki):
    """The readiness check (wait for "listening") may rely on every port answering once it sees the line."""
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", "--port", "0", "--web", "0",
                             "--opcua", "0", "--tls-port", "0", *_tls_flags(pki)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline() for _ in range(4)]
        assert "listening on 127.0.0.1:" in lines[0], lines + [proc.stderr.read() if proc.poll() else ""]
        ports = {int(p) for p in re.findall(r"127\.0\.0\.1:(\d+)", "".join(lines))}
        assert len(ports) == 4 and 0 not in ports, lines
        assert "Modbus/TCP Security" in lines[1] and "instructor station" in lines[2] and "OPC UA" in lines[3]
        for port in ports:   # every one of them accepts a connection now
            socket.create_connection(("127.0.0.1", port), timeout=5).close()
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0 and "Traceback" not in err, err


def test_an_address_this_machine_does_not_have_names_the_host_flag():
    """192.0.2.1 is TEST-NET-1 (RFC 5737): never an address of this machine."""
    out = _serve("--host", "192.0.2.1", "--port", "0")
    assert (out.returncode, out.stdout) == (2, "")
    assert out.stderr.splitlines() == ["valve-emulator serve: error: --host 192.0.2.1: cannot assign requested address"]
