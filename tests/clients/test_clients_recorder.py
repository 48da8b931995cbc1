"""The recorder: killed with SIGKILL it leaves only whole lines, wall-time and generic channels, bad flags and
unreachable devices, and every client's ``python -m valve_emulator.clients.NAME --help``."""

from __future__ import annotations

import asyncio
import math
import signal
import socket
import sys
import warnings

import numpy as np
import pytest

from valve_emulator.clients import monitor, pi_controller, recorder, scenario
from valve_emulator.clients._channels import emulator_channels
from valve_emulator.clients.recorder import main
from valve_emulator.config import server_from_mapping
from valve_emulator.device.server import EmulatorServer
from valve_emulator.recordings.recording import RecordingWarning, read_csv

pytestmark = pytest.mark.usefixtures("no_task_leak")

LOOP = {"valve": {"S": 2.0, "J": 1.0}, "plant": {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]},
        "controller": {"kc": 0.2, "ti": 10.0, "sp": 0.0, "sp_steps": [[1.0, 1.0]]}}


def config(**device):
    return server_from_mapping({"device": {"tick": 0.1, **device}, "loops": [{"unit": 1, **LOOP}]})


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
async def test_sigkill_leaves_a_csv_whose_every_complete_line_parses(tmp_path):
    out = tmp_path / "killed.csv"
    async with EmulatorServer(config(), time_scale=20.0) as srv:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "valve_emulator.clients.recorder", "--port", str(srv.port),
            "--step", "0.5", "--period", "0.025",
            "--out", str(out), "--quiet", stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
        try:
            for _ in range(3000):       # bounded wait for rows, paced by the device (no wall-clock sleep)
                await srv.device.wait_for_tick(srv.device.ticks + 2)
                if out.exists() and out.read_bytes().count(b"\n") > 40:
                    break
            proc.send_signal(signal.SIGKILL)
            await proc.wait()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
    assert proc.returncode == -signal.SIGKILL
    data = out.read_bytes()
    lines = data.split(b"\n")
    complete, partial = lines[:-1], lines[-1]       # the last piece lacks its newline (or is empty)
    header = complete[0].decode().split(",")
    assert header[:5] == ["t", "sp", "op", "mv", "pv"] and len(complete) > 40
    for line in complete[1:]:
        cells = line.decode().split(",")
        assert len(cells) == len(header), line
        values = [float(c) if c else math.nan for c in cells]
        assert all(math.isfinite(v) for v in values[:1] + values[2:5]), line
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RecordingWarning)      # a cut last line is dropped with a warning
        # the format is what matters here; the sampling of a starved subprocess may be uneven
        rec = read_csv(out, gap_factor=None)
    assert len(rec) >= len(complete) - 1 and np.all(np.diff(rec.t) > 0)
    assert partial == b"" or len(rec) in (len(complete) - 1, len(complete))


async def test_wall_time_constant_set_point_and_generic_channels(tmp_path):
    """Pointed at registers by address as for a foreign device: PV from the scaled int16 (% of range),
    no device time (wall seconds), a constant set point column, no extras."""
    out = tmp_path / "generic.csv"
    async with EmulatorServer(config(), time_scale=20.0) as srv:
        task = asyncio.create_task(asyncio.to_thread(main, [
            "--port", str(srv.port), "--out", str(out), "--period", "0.02", "--duration", "0.5", "--quiet",
            "--time", "none", "--sp", "1.5", "--mv", "none", "--no-extras", "--op", "holding:0:uint16:100",
            "--pv", "hr:4:int16:500:5000"]))
        assert await task == 0
        pv_now = srv.device.bank.pv[0]
    rec = read_csv(out, gap_factor=None)  # wall-clock polling every 20 ms: a loaded machine leaves gaps
    assert rec.columns == ("t", "sp", "op", "mv", "pv")
    assert 10 <= len(rec) <= 30 and rec.t[0] == 0.0 and rec.t[-1] < 1.0          # wall seconds
    assert np.all(rec.sp == 1.5) and np.all(np.isnan(rec.mv))
    assert rec.pv[-1] == pytest.approx(pv_now, abs=0.05)    # 0.01 % of a 20-unit range is 0.002


async def test_set_point_served_by_an_internal_controller_is_recorded(tmp_path):
    out = tmp_path / "pi.csv"
    # 0.5 device s is 100 ms of wall time at this scale: a poll on a loaded machine (CI's first phase runs two
    # busy workers beside it) still lands on the device's grid, where 25 ms at a scale of 20 missed it at times
    async with EmulatorServer(config(), time_scale=5.0) as srv:
        summary = await recorder.record(recorder.RecorderOptions(
            out=out, channels=emulator_channels(), port=srv.port, step=0.5, period=0.1, until=5.0))
    rec = read_csv(out)
    assert summary.rows == len(rec) and rec.sp[0] == 0.0 and rec.sp[-1] == 1.0   # sp_steps [[1.0, 1.0]]
    assert np.mean(np.abs(np.diff(rec.t) - 0.5) < 1e-6) >= 0.8                  # the device's time grid


def test_bad_flags_and_no_device(tmp_path, capsys):
    out = tmp_path / "x.csv"
    assert main(["--out", str(out), "--pv", "coils:3"]) == 2
    assert "--pv: 'coils:3'" in capsys.readouterr().err
    assert main(["--out", str(out), "--period", "0"]) == 2
    assert main(["--out", str(out), "--step", "1", "--time", "none"]) == 2     # a bad flag combination
    assert "needs the --time channel" in capsys.readouterr().err
    port = free_port()
    assert main(["--out", str(out), "--port", str(port), "--timeout", "0.5"]) == 1
    assert f"no Modbus TCP server at 127.0.0.1:{port}" in capsys.readouterr().err


@pytest.mark.parametrize("module", [recorder, pi_controller, monitor, scenario], ids=lambda m: m.__name__)
def test_main_help(module, capsys):
    with pytest.raises(SystemExit) as exc:
        module.main(["--help"])
    assert exc.value.code == 0 and "usage: python -m valve_emulator.clients." in capsys.readouterr().out


@pytest.mark.slow
async def test_every_client_runs_as_a_module():
    names = ("recorder", "pi_controller", "monitor", "scenario")
    procs = [await asyncio.create_subprocess_exec(sys.executable, "-m", f"valve_emulator.clients.{n}", "--help",
                                                  stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
             for n in names]
    results = [await asyncio.wait_for(p.communicate(), timeout=60) for p in procs]
    for name, proc, (out, err) in zip(names, procs, results):
        assert proc.returncode == 0, err.decode()
        assert f"python -m valve_emulator.clients.{name}" in out.decode()
