"""The twin from the command line: ``diagnose --twin``, ``simulate --replay [--replay-sp]``, ``serve TWIN.yaml``.

Known truth: the level loop of the proof table (S = 3 %, J = 1.5 %, PV in m) simulated with its set point kept,
concealed (noise, cut mid-cycle), diagnosed against its nominal model.
"""

from __future__ import annotations

import json
import re
import signal
import struct
import subprocess
import sys

import numpy as np
import pytest
from pymodbus.client import ModbusTcpClient

from valve_emulator.benchmark.cases import CASES, generate
from valve_emulator.cli import main
from valve_emulator.config import load_loop, load_server, write_loop
from valve_emulator.device.registers import address_of
from valve_emulator.diagnosis.fit.data import HELD_OUT, fit_percent
from valve_emulator.recordings import read_recording
from valve_emulator.recordings.recording import Recording, write_csv
from valve_emulator.simulation.limit_cycle import measure_limit_cycle
from valve_emulator.simulation.loop import simulate_loop

CASE = next(c for c in CASES if c.name == "stiction, level loop")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """rec.csv (with SP), nominal.yaml, and what ``diagnose --twin`` wrote: twin.yaml and out.json."""
    d = tmp_path_factory.mktemp("twin")
    _, nominal, true = generate(CASE, duration=400.0)
    run = simulate_loop(true)
    k = int(round(CASE.cut / run.dt))
    write_csv(Recording(run.t[k:] - run.t[k], run.sp[k:], run.op[k:], None, run.pv[k:]), d / "rec.csv")
    write_loop(nominal, d / "nominal.yaml")
    assert main(["diagnose", str(d / "rec.csv"), "--model", str(d / "nominal.yaml"), "--twin", str(d / "twin.yaml"),
                 "--json", str(d / "out.json"), "--pv-units", "m", "--quiet"]) == 0
    return d


def test_diagnose_writes_a_twin_that_loads_with_its_provenance(files):
    text = (files / "twin.yaml").read_text(encoding="utf-8")
    assert text.startswith("# Twin of ") and "# valve.S, valve.J: stiction found" in text
    cfg = load_loop(files / "twin.yaml")
    assert cfg.plant.units == "m" and cfg.controller.mode == "auto"
    found = [cfg.valve.S, cfg.valve.J]
    assert found == pytest.approx([3.0, 1.5], abs=0.3)


def test_the_open_loop_replay_fits_within_two_points_of_fit_after(files, tmp_path, capsys):
    out = tmp_path / "sim.csv"
    assert main(["simulate", str(files / "twin.yaml"), "--replay", str(files / "rec.csv"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    rec, sim = read_recording(files / "rec.csv").recording, read_recording(out).recording
    assert len(sim) == len(rec) and np.allclose(sim.t, rec.t - rec.t[0])
    a = int(round((1.0 - HELD_OUT) * len(rec)))
    fit = fit_percent(rec.pv[a:], sim.pv[a:])
    assert abs(fit - json.loads((files / "out.json").read_text())["fit_after"]) <= 2.0
    assert f"PV fit {fit:.1f} %" in printed


def test_the_closed_loop_replay_cycles_like_the_recording(files, tmp_path):
    out = tmp_path / "cl.csv"
    assert main(["simulate", str(files / "twin.yaml"), "--replay", str(files / "rec.csv"), "--replay-sp",
                 "--out", str(out)]) == 0
    rec, sim = read_recording(files / "rec.csv").recording, read_recording(out).recording
    want, got = measure_limit_cycle(rec.t, rec.pv), measure_limit_cycle(sim.t, sim.pv)
    assert got.sustained
    assert got.period == pytest.approx(want.period, rel=0.2) and got.amplitude == pytest.approx(want.amplitude, rel=0.2)


def test_bad_replays_are_one_error_line_naming_the_file_and_write_nothing(files, tmp_path, capsys):
    rec = read_recording(files / "rec.csv").recording
    (tmp_path / "nosp.csv").write_text("t,op,pv\n" + "".join(f"{t},{o},{p}\n" for t, o, p in
                                                          zip(rec.t, rec.op, rec.pv)), encoding="utf-8")
    (tmp_path / "broken.csv").write_text("t,sp,op,mv,pv\n0,1,2\n", encoding="utf-8")
    out = tmp_path / "out.csv"
    for args, name in ((["--replay", str(tmp_path / "nosp.csv"), "--replay-sp"], "nosp.csv"),
                       (["--replay", str(tmp_path / "broken.csv")], "broken.csv"),
                       (["--replay", str(tmp_path / "missing.csv")], "missing.csv"),
                       (["--replay-sp"], "--replay")):
        assert main(["simulate", str(files / "twin.yaml"), *args, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0], err
        assert not out.exists()


def test_diagnose_without_a_fitted_model_writes_no_twin(tmp_path, capsys):
    t = np.arange(400.0)
    write_csv(Recording(t, None, 50.0 + 0.0 * t, None, np.sin(t / 7.0)), tmp_path / "flat.csv")
    assert main(["diagnose", str(tmp_path / "flat.csv"), "--twin", str(tmp_path / "t.yaml"), "--quiet"]) == 2
    assert "flat.csv" in capsys.readouterr().err and not (tmp_path / "t.yaml").exists()


def _float(client, name: str) -> float:
    rr = client.read_holding_registers(address_of(name), count=2, device_id=1)
    assert not rr.isError()
    return struct.unpack(">f", struct.pack(">HH", *rr.registers))[0]


def test_serve_twin_answers_with_pv_and_sp_in_the_recordings_units(files):
    cfg = load_loop(files / "twin.yaml")
    proc = subprocess.Popen([sys.executable, "-m", "valve_emulator", "serve", str(files / "twin.yaml"), "--port",
                             "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        m = re.search(r"listening on ([\d.]+):(\d+), unit ids 1 \(twin_rec\)", line)
        assert m, line + (proc.stderr.read() if proc.poll() is not None else "")
        client = ModbusTcpClient(m.group(1), port=int(m.group(2)), timeout=10)
        assert client.connect()
        rec = read_recording(files / "rec.csv").recording
        assert cfg.controller.sp == pytest.approx(float(np.median(rec.sp)))   # the loop's usual set point, m
        assert _float(client, "sp_f32") == pytest.approx(cfg.controller.sp, abs=1e-5)
        lo, hi = cfg.plant.pv_range
        assert lo < _float(client, "pv_f32") < hi
        client.close()
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=5)
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_registers_and_station_show_the_twins_units(files, capsys):
    assert main(["registers", str(files / "twin.yaml"), "--format", "json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out) if r["table"] == "holding"}
    assert rows["pv_f32"]["units"] == rows["sp_f32"]["units"] == "m"


async def test_the_station_shows_the_twin_by_name_and_units(files):
    from valve_emulator.device.server import EmulatorServer
    from valve_emulator.station.core import Station

    async with EmulatorServer(load_server(files / "twin.yaml"), host="127.0.0.1", port=0, time_scale=0.0) as srv:
        loop = Station(srv.device).state(instructor=False)["loops"][0]
    assert loop["name"] == "twin_rec" and loop["pv_units"] == "m"
