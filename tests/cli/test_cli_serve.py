"""`valve-emulator serve` as a user runs it (a subprocess), and `valve-emulator registers`."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time

import pytest
from pymodbus.client import ModbusTcpClient

from valve_emulator.cli import main


def start_serve(*args):
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", "--port", "0", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    m = re.search(r"listening on ([\d.]+):(\d+), unit ids 1 \(concentration_undershoot\)", line)
    assert m, line + proc.stderr.read() if proc.poll() is not None else line
    return proc, m.group(1), int(m.group(2))


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_serve_default_device_answers_and_stops_within_a_second(sig):
    proc, host, port = start_serve("--time-scale", "10")
    try:
        assert host == "127.0.0.1"  # bound to loopback unless told otherwise
        client = ModbusTcpClient(host, port=port, timeout=10)  # generous: CI machines can be loaded
        assert client.connect()
        rr = client.read_holding_registers(0, count=4, device_id=1)
        assert not rr.isError() and rr.registers[0] == 5000  # OP 50.00 %
        assert client.read_holding_registers(0, count=1, device_id=9).exception_code == 0x0B
        client.close()
        t0 = time.monotonic()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=5)
        assert time.monotonic() - t0 < 1.0
        assert proc.returncode == 0 and "stopped" in out
        assert "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_serve_warns_when_bound_to_all_interfaces():
    proc, host, _ = start_serve("--host", "0.0.0.0")
    try:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=5)
        assert "all interfaces" in err and "no authentication" in err
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.parametrize("argv, words", [
    (["serve", "--port", "70000"], "--port"),
    (["serve", "--time-scale", "0"], "--time-scale"),
    (["serve", "no/such/file.yaml"], "no/such/file.yaml"),
    (["serve", "--lockstep", "--time-scale", "5"], "--lockstep and --time-scale"),
    (["serve", "--lockstep", "--processes", "2", "x.yaml"], "--lockstep with --processes"),
    (["serve", "--lockstep", "--read-only", "--port", "0"], "would refuse the step writes"),
])
def test_serve_bad_flags_and_files_are_clear_errors(argv, words, capsys):
    assert main(argv) == 2
    assert words in capsys.readouterr().err


def test_registers_command_prints_json_with_the_documented_keys(capsys):
    assert main(["registers", "--format", "json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert all(set(r) == {"name", "table", "address", "reference", "type", "scale", "units", "access"} for r in rows)
    holding = {r["name"]: r for r in rows if r["table"] == "holding"}
    for name in ("op_pct", "op_ma", "mv_pct", "pv"):
        assert name in holding
    assert holding["op_pct"]["access"].startswith("RW") and holding["op_ma"]["access"].startswith("RW")
    assert main(["registers", "--format", "csv"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == "name,table,address,reference,type,scale,units,access"
