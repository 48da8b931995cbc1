"""Several server processes share one fleet: the partition, `serve --processes N`, `--process-index I`."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time

import pytest
from pymodbus.client import ModbusTcpClient

from valve_emulator.cli import main
from valve_emulator.config import partition, server_from_mapping, server_slice
from valve_emulator.config.layout import unit_ranges

PLANT = {"fopdt": {"gain": 1.0, "tau": 5.0}}
FLEET_YAML = """device: {tick: 0.1}
loops:
  - {unit: 200, plant: {fopdt: {gain: 2.0, tau: 3.0}}, valve: {op0: 30.0}}
fleet:
  count: 50
  loops_per_unit: 10
  base: {valve: {S: 2.0, J: 1.0}, plant: {fopdt: {gain: 1.0, tau: 5.0}}}
  vary: {S: [1.0, 3.0]}
"""


def fleet(count, per_unit, extra_units=()):
    loops = [{"unit": u, "plant": PLANT} for u in extra_units]
    return server_from_mapping({"fleet": {"count": count, "loops_per_unit": per_unit, "base": {"plant": PLANT}},
                                **({"loops": loops} if loops else {})})


# --- the partition ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("count, per_unit, parts, sizes", [
    (10_000, 100, 2, [5000, 5000]),
    (1000, 100, 3, [300, 400, 300]),
    (250, 100, 3, [100, 100, 50]),        # uneven units: no slice is empty
    (7, 1, 7, [1] * 7),
])
def test_partition_gives_whole_units_balanced_and_in_order(count, per_unit, parts, sizes):
    cfg = fleet(count, per_unit)
    slices = partition(cfg, parts)
    assert [len(s.loops) for s in slices] == sizes
    assert [i for s in slices for i in s.loops] == list(range(count))      # contiguous, every loop once
    units = [u for s in slices for u in s.units]
    assert len(units) == len(set(units))                                  # a unit lives in one slice


def test_a_slice_keeps_addresses_and_settings_and_the_errors_are_clear():
    cfg = fleet(30, 10, extra_units=(100, 101))
    part = server_slice(cfg, 1, 2)
    assert part.device == cfg.device
    assert [(lp.device.unit, lp.device.block) for lp in part.loops] == [(2, b) for b in range(10)] + [
        (3, b) for b in range(10)]
    assert [lp.name for lp in server_slice(cfg, 0, 2).loops][:2] == ["loop_100", "loop_101"]
    with pytest.raises(ValueError, match=r"processes \(6\) must be <= the number of unit ids in the config \(5\)"):
        partition(cfg, 6)
    with pytest.raises(ValueError, match=r"process index must be 0\.\.1"):
        server_slice(cfg, 2, 2)
    assert unit_ranges([1, 2, 3, 7, 9, 10]) == "1-3, 7, 9-10"


# --- the command line -----------------------------------------------------------------------------------

@pytest.fixture
def fleet_file(tmp_path):
    path = tmp_path / "fleet.yaml"
    path.write_text(FLEET_YAML, encoding="utf-8")
    return path


def _layout(proc, processes):
    """The parent's layout lines: {process: (pid, port, units text)}."""
    found, lines = {}, []
    while len(found) < processes:
        line = proc.stdout.readline()
        assert line, "".join(lines) + (proc.stderr.read() if proc.poll() is not None else "")
        lines.append(line)
        m = re.search(r"process (\d+) \(pid (\d+)\) listening on 127\.0\.0\.1:(\d+), units ([\d, -]+) \(", line)
        if m:
            found[int(m.group(1))] = (int(m.group(2)), int(m.group(3)), m.group(4))
    return found, lines


def _read(port, unit, address=0, count=1):
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    assert client.connect()
    try:
        return client.read_holding_registers(address, count=count, device_id=unit)
    finally:
        client.close()


def test_serve_processes_prints_the_layout_each_port_serves_its_units_and_stops_within_a_second(fleet_file):
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", str(fleet_file), "--processes", "2",
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        found, lines = _layout(proc, 2)
        assert "2 processes serve 51 loops" in "".join(lines)
        # 51 loops: unit 200 (1 loop) and units 1..5 (10 each); process 0 takes unit 200 and units 1-2
        assert found[0][2] == "200, 1-2" and found[1][2] == "3-5"
        (pid0, port0, _), (_, port1, _) = found[0], found[1]
        assert _read(port0, 200).registers == [3000]                       # op0 30 %
        rr = _read(port1, 5, 9 * 32, 4)                                     # unit 5, block 9: the last loop
        assert not rr.isError() and rr.registers[0] == 5000
        assert _read(port1, 1).exception_code == 0x0B                       # unit 1 lives behind port 0
        assert _read(port0, 5).exception_code == 0x0B
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=5)
        assert time.monotonic() - t0 < 1.0
        assert proc.returncode == 0 and out.rstrip().endswith("valve-emulator: stopped"), out + err
        assert "Traceback" not in err
        with pytest.raises(ProcessLookupError):
            os.kill(pid0, 0)                                                # the child is gone, not orphaned
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_when_one_process_dies_the_parent_stops_the_others_and_fails(fleet_file):
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", str(fleet_file), "--processes", "2",
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        found, _ = _layout(proc, 2)
        os.kill(found[1][0], signal.SIGKILL)
        out, err = proc.communicate(timeout=5)
        assert proc.returncode == 1 and "process 1 exited with status -9; stopping the others" in err
        assert out.rstrip().endswith("valve-emulator: stopped")
        with pytest.raises(ProcessLookupError):
            os.kill(found[0][0], 0)                                         # the survivor was stopped too
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _free_port_pair() -> int:
    for _ in range(50):
        with socket.socket() as a:
            a.bind(("127.0.0.1", 0))
            base = a.getsockname()[1]
            if base >= 65535:
                continue
            with socket.socket() as b:
                try:
                    b.bind(("127.0.0.1", base + 1))
                except OSError:
                    continue
                return base
    pytest.skip("no two consecutive free ports")


def test_process_index_serves_one_slice_on_port_plus_index(fleet_file):
    base = _free_port_pair()
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", str(fleet_file), "--processes", "2",
                             "--process-index", "1", "--port", str(base)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert f"process 1/2 listening on 127.0.0.1:{base + 1}, unit ids 3-5 (30 loops, up to 10 per unit)" in line, \
            line + (proc.stderr.read() if proc.poll() is not None else "")
        assert not _read(base + 1, 4, 32, 1).isError() and _read(base + 1, 200).exception_code == 0x0B
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=5)
        assert proc.returncode == 0 and "stopped" in out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("argv, words", [
    (["--processes", "7"], "processes (7) must be <= the number of unit ids in the config (6)"),
    (["--processes", "2", "--process-index", "2"], "--process-index must be 0..1 for --processes 2, got 2"),
    (["--processes", "0"], "--processes must be >= 1"),
    (["--processes", "2", "--record", "x.csv"], "--record with --processes"),
    (["--record", "x.csv"], "recording needs one loop per unit id"),
])
def test_bad_process_flags_are_clear_errors(fleet_file, argv, words, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["serve", str(fleet_file), "--port", "0", *argv]) == 2
    assert words in capsys.readouterr().err
