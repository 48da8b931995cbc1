"""Faults: signals stop cleanly and keep the recording whole, SIGKILL loses no complete line, a
failing disk is reported without stopping the device, a bad config reload keeps the running config."""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import re
import signal
import struct
import sys
import time
import warnings
from pathlib import Path

import pytest

from valve_emulator.config import load_server
from valve_emulator.device.record import EXTRA_COLUMNS, TickRecorder, recording_paths
from valve_emulator.device.runtime import reload_config
from valve_emulator.device.server import EmulatorServer
from valve_emulator.recordings.recording import read_csv

pytestmark = pytest.mark.usefixtures("no_task_leak")

CONFIG = """\
name: hup
plant: {num: [3.0], den: [10.0, 1.0], pv_range: [-10.0, 10.0]}
device:
  unit: 1
  tick: 0.1
  read_only: false
  max_connections: 64
"""
HEADER = "t,sp,op,mv,pv," + ",".join(EXTRA_COLUMNS)


# --- helpers ----------------------------------------------------------------------------------------------

async def _serve(*args):
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "valve_emulator", "serve", "--port", "0", *args,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    line = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode()
    m = re.search(r"listening on [\d.]+:(\d+)", line)
    assert m, line + (await proc.stderr.read()).decode()
    return proc, int(m.group(1))


async def _line(stream, needle: str, timeout: float = 10.0) -> str:
    """The next line of a subprocess stream that contains ``needle`` (bounded wait)."""
    async def find():
        while line := (await stream.readline()).decode():
            if needle in line:
                return line
        raise AssertionError(f"stream ended without {needle!r}")
    return await asyncio.wait_for(find(), timeout)


async def _write_op(port: int, value: int) -> tuple[int, bytes]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(struct.pack(">HHHBBHH", 1, 0, 6, 1, 6, 0, value))
    answer = await asyncio.wait_for(reader.readexactly(9), 5)
    if answer[7] == 6:
        answer += await reader.readexactly(3)
    writer.close()
    await writer.wait_closed()
    return answer[7], answer[8:]


async def _until(predicate, timeout: float = 10.0) -> None:
    """Bounded polling on observable state (not a synchronising sleep)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.01)


def _lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").split("\n") if path.exists() else [""]


async def _stop(proc, sig=signal.SIGTERM) -> float:
    t0 = time.monotonic()
    proc.send_signal(sig)
    await asyncio.wait_for(proc.wait(), 10)
    return time.monotonic() - t0


# --- config reload ----------------------------------------------------------------------------------------

async def test_reload_applies_live_settings_and_an_invalid_file_changes_nothing(tmp_path, fake_bank_cls, caplog):
    path = tmp_path / "dev.yaml"
    path.write_text(CONFIG)
    cfg = load_server(path)
    async with EmulatorServer(cfg, bank=fake_bank_cls.for_config(cfg), time_scale=0) as srv:
        path.write_text(CONFIG.replace("max_connections: 64", "max_connections: 0"))
        with caplog.at_level(logging.ERROR):
            assert reload_config(srv, path) is False
        message = caplog.records[-1].getMessage()
        assert "keeping the running config" in message
        assert "dev.yaml:7: device.max_connections must be in 1..65535, got 0" in message
        assert srv.config is cfg and srv.guard.max_connections == 64
        path.unlink()
        assert reload_config(srv, path) is False and "cannot read the file" in caplog.records[-1].getMessage()
        assert srv.config is cfg
        path.write_text(CONFIG.replace("read_only: false", "read_only: true"))
        assert reload_config(srv, path) is True
        assert await _write_op(srv.port, 2500) == (0x86, b"\x01")
        # the command line's --read-only wins over the file, also on reload
        path.write_text(CONFIG)
        assert reload_config(srv, path, read_only=True) is True
        assert await _write_op(srv.port, 2500) == (0x86, b"\x01")
        assert reload_config(srv, path) is True
        assert (await _write_op(srv.port, 2500))[0] == 6
        assert reload_config(srv, None) is False


async def test_sighup_reloads_and_keeps_the_running_config_when_the_file_is_bad(tmp_path):
    path = tmp_path / "dev.yaml"
    path.write_text(CONFIG)
    proc, port = await _serve(str(path))
    try:
        path.write_text(CONFIG.replace("max_connections: 64", "max_connections: 0"))
        proc.send_signal(signal.SIGHUP)
        line = await _line(proc.stderr, "config reload failed")
        assert "keeping the running config" in line and "device.max_connections must be in 1..65535" in line
        assert (await _write_op(port, 2500))[0] == 6                     # still serving, still writable
        path.write_text(CONFIG.replace("read_only: false", "read_only: true"))
        proc.send_signal(signal.SIGHUP)
        await _line(proc.stdout, f"reloaded {path}")
        assert await _write_op(port, 3000) == (0x86, b"\x01")
        assert await _stop(proc) < 1.0 and proc.returncode == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


# --- recording while the process dies ---------------------------------------------------------------------

def _check_recording(path: Path) -> list[list[str]]:
    """Every complete line is a whole row; returns the rows (a partial last line is allowed)."""
    lines = _lines(path)
    complete, partial = lines[:-1], lines[-1]
    assert complete[0] == HEADER
    rows = [line.split(",") for line in complete[1:]]
    for row in rows:
        assert len(row) == len(HEADER.split(",")), row
        [float(cell) for cell in row if cell]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # the partial last line, if any, is dropped with a warning
        recording = read_csv(path)
    assert len(recording) == len(rows) or (partial and len(recording) == len(rows) + 1)
    ticks = [int(float(row[-1])) for row in rows]
    assert ticks == list(range(ticks[0], ticks[0] + len(ticks))), "a tick without its line"
    return rows


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT])
async def test_recording_survives_the_end_of_the_emulator(tmp_path, sig):
    path = tmp_path / "rec.csv"
    proc, _ = await _serve("--time-scale", "20", "--record", str(path))
    try:
        await _line(proc.stdout, "recording to")
        await _until(lambda: len(_lines(path)) > 102)   # header + 100 rows + the rest
        elapsed = await _stop(proc, sig)
        if sig != signal.SIGKILL:
            assert elapsed < 1.0 and proc.returncode == 0
            assert path.read_text().endswith("\n")       # stopped cleanly: no partial line at all
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert len(_check_recording(path)) >= 100


# --- recorder in process -------------------------------------------------------------------------------

def _server(fake_bank_cls, n=1, **kw):
    from valve_emulator.config import server_from_mapping
    cfg = server_from_mapping({"device": {"tick": 0.1}, "loops": [
        {"unit": u, "plant": {"num": [3.0], "den": [10.0, 1.0]}} for u in range(1, n + 1)]})
    return EmulatorServer(cfg, bank=fake_bank_cls.for_config(cfg), **kw)


async def test_recorder_writes_one_row_per_tick_of_every_loop(tmp_path, fake_bank_cls):
    async with _server(fake_bank_cls, 3, time_scale=float("inf")) as srv:
        async with TickRecorder(srv.device, tmp_path / "run.csv", units=[1, 3]) as rec:
            await srv.device.wait_for_tick(srv.device.ticks + 50)
        ticks = srv.device.ticks
    assert set(rec.paths) == {1, 3} and rec.paths[3].name == "run_u003.csv"
    for unit in (1, 3):
        recording = read_csv(rec.paths[unit])
        assert recording.extra["tick"][-1] >= 50
        assert list(recording.extra["tick"]) == list(range(int(recording.extra["tick"][0]), ticks + 1))[:len(recording)]
        assert recording.t == pytest.approx(0.1 * (recording.extra["tick"] - 1))
    assert not (tmp_path / "run_u002.csv").exists()


async def test_a_full_disk_is_reported_once_and_the_device_keeps_ticking(tmp_path, fake_bank_cls, caplog):
    caplog.set_level(logging.ERROR, logger="valve_emulator.device.record")
    async with _server(fake_bank_cls, 1, time_scale=float("inf")) as srv:
        async with TickRecorder(srv.device, "/dev/full") as rec:        # ENOSPC on the first flush
            k = await srv.device.wait_for_tick(srv.device.ticks + 20)
        assert rec.failed == {1: "No space left on device"} and k >= 20
    assert len(caplog.records) == 1 and "/dev/full" in caplog.records[0].getMessage()


class _FailingFile:
    """A file whose disk fails (full, or remounted read-only) from now on."""

    def __init__(self, err: int) -> None:
        self.err = err

    def write(self, text: str) -> int:
        raise OSError(self.err, os.strerror(self.err))

    flush = write

    def close(self) -> None:
        self.write("")


@pytest.mark.parametrize("err", [errno.ENOSPC, errno.EROFS])
async def test_a_disk_failing_mid_run_stops_only_that_file(tmp_path, fake_bank_cls, caplog, err):
    caplog.set_level(logging.ERROR, logger="valve_emulator.device.record")
    async with _server(fake_bank_cls, 2, time_scale=float("inf")) as srv:
        async with TickRecorder(srv.device, tmp_path / "r.csv") as rec:
            await _until(lambda: rec.rows >= 10)
            good = rec.paths[2].read_text()
            rec._writers[1]._fh = _FailingFile(err)   # unit 1's disk fails; unit 2 is on another
            k = srv.device.ticks
            await srv.device.wait_for_tick(k + 30)
        assert set(rec.failed) == {1} and srv.device.ticks >= k + 30
    assert len(caplog.records) == 1 and "r_u001.csv" in caplog.records[0].getMessage()
    assert read_csv(rec.paths[1]).t.size >= 4              # what was written before stays whole
    assert len(read_csv(rec.paths[2])) > len(good.splitlines())   # the other file went on


def test_recording_paths_and_bad_units(fake_bank_cls):
    assert recording_paths("a/x.csv", [4]) == {4: Path("a/x.csv")}
    assert recording_paths("x.csv", [1, 12]) == {1: Path("x_u001.csv"), 12: Path("x_u012.csv")}
    srv = _server(fake_bank_cls, 2, time_scale=0)
    for units in ([], [3], [1, 1]):
        with pytest.raises(ValueError, match="record units"):
            TickRecorder(srv.device, "x.csv", units=units)


# --- command-line flags -----------------------------------------------------------------------------------

async def test_serve_read_only_flag_refuses_writes_with_0x01():
    proc, port = await _serve("--read-only", "--max-connections", "5")
    try:
        assert await _write_op(port, 2500) == (0x86, b"\x01")
        assert await _stop(proc, signal.SIGINT) < 1.0 and proc.returncode == 0
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


@pytest.mark.parametrize("argv, words", [
    (["serve", "--max-connections", "0"], "--max-connections must be 1..65535"),
    (["serve", "--record-unit", "1"], "--record-unit needs --record"),
    (["serve", "--record", "x.csv", "--record-unit", "4"], "--record-unit 4: the device has units [1]"),
])
def test_serve_flag_errors(argv, words, capsys):
    from valve_emulator.cli import main

    assert main(argv) == 2
    assert words in capsys.readouterr().err
