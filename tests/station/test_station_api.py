"""The station's HTTP API with aiohttp's test client against a real emulator (Modbus on 127.0.0.1)."""

import asyncio
import csv
import json
import time

import numpy as np
import pytest
from station_helpers import JSON, PLANT, station_config

from valve_emulator.config import ConfigError, server_from_mapping
from valve_emulator.device.registers import address_of
from valve_emulator.device.snapshots import BacktrackRing

pytestmark = pytest.mark.usefixtures("no_task_leak")


async def _post(client, path, body=None, **kw):
    return await client.post(path, data=json.dumps({} if body is None else body), headers=JSON, **kw)


async def _tick_register(modbus):
    rr = await modbus.read_holding_registers(address_of("tick"), count=2, device_id=1)
    assert not rr.isError(), rr
    return rr.registers[0] << 16 | rr.registers[1]


async def test_state_has_the_documented_fields(station_for):
    srv, station, client = await station_for()
    srv.device.advance(3)
    resp = await client.get("/api/state")
    assert resp.status == 200
    state = await resp.json()
    assert {"time", "running", "time_scale", "loops"} <= set(state)
    assert state["time"] == pytest.approx(0.2)
    loop = state["loops"][0]
    for key in ("unit", "name", "sp", "pv", "op", "mv", "mode", "S", "J", "status"):
        assert key in loop
    assert (loop["unit"], loop["name"], loop["mode"], loop["S"], loop["J"]) == (1, "FIC101", "auto", 5.0, 2.0)
    assert state["loops"][1]["mode"] == "external"
    assert set(loop["status"]) == {"stuck", "moving", "saturated", "fault"}


async def test_freeze_holds_simulated_time_and_the_modbus_tick(station_for, client_for):
    srv, station, client = await station_for(station_config(tick=0.01), time_scale=1.0)
    modbus = await client_for(srv)
    await srv.device.wait_for_tick(5)
    assert (await _post(client, "/api/freeze")).status == 200
    t0, tick0 = (await (await client.get("/api/state")).json())["time"], await _tick_register(modbus)
    await asyncio.sleep(0.3)
    assert (await (await client.get("/api/state")).json())["time"] == t0
    assert await _tick_register(modbus) == tick0
    assert (await _post(client, "/api/run")).status == 200
    await srv.device.wait_for_tick(srv.device.ticks + 5)
    assert await _tick_register(modbus) > tick0


@pytest.mark.realtime   # a wall-clock rate: with the other tests beside it, it measured the machine
async def test_speed_five_runs_five_times_faster_within_ten_percent(station_for):
    srv, station, client = await station_for(station_config(tick=0.05), time_scale=1.0)
    await srv.device.wait_for_tick(2)
    assert (await _post(client, "/api/speed", {"time_scale": 5})).status == 200
    s0, w0 = (await (await client.get("/api/state")).json())["time"], time.monotonic()
    await asyncio.sleep(1.5)
    s1, w1 = (await (await client.get("/api/state")).json())["time"], time.monotonic()
    assert (s1 - s0) / (w1 - w0) == pytest.approx(5.0, rel=0.10)


def _trace(device, ticks):
    rows = []
    for _ in range(ticks):
        device.advance(1)
        b = device.bank
        rows.append((b.sample_time, b.op.copy(), b.mv, b.pv.copy(), b._vstate.copy()))
    return rows


async def test_snapshot_restore_over_http_is_exact(station_for):
    srv, station, client = await station_for(station_config(noise=0.05))
    dev = srv.device
    dev.advance(50)
    assert (await _post(client, "/api/loops/2", {"op": 63.0})).status == 200
    dev.advance(30)
    resp = await _post(client, "/api/snapshots", {"name": "lesson-1"})
    assert resp.status == 201, await resp.text()
    saved = _trace(dev, 100)
    resp = await _post(client, "/api/snapshots/lesson-1/restore")
    assert resp.status == 200
    restored = _trace(dev, 100)
    for a, b in zip(saved, restored):
        assert a[0] == b[0]
        for x, y in zip(a[1:], b[1:]):
            np.testing.assert_array_equal(x, y)
    listing = await (await client.get("/api/snapshots")).json()
    assert [s["name"] for s in listing["snapshots"]] == ["lesson-1"]
    assert (await client.delete("/api/snapshots/lesson-1", headers=JSON)).status == 200
    assert (await client.delete("/api/snapshots/lesson-1", headers=JSON)).status == 404


async def test_backtrack_points_are_listed_and_restorable(station_for):
    srv, station, client = await station_for(backtrack=BacktrackRing(interval=2.0, size=5))
    srv.device.advance(70)
    names = [s["name"] for s in (await (await client.get("/api/snapshots")).json())["backtrack"]]
    assert len(names) == 4
    resp = await _post(client, f"/api/snapshots/{names[1]}/restore")
    assert resp.status == 200
    assert station.bank.sample_time == pytest.approx(2.0)


async def test_a_ramped_malfunction_over_http_reaches_its_value_at_the_ramps_end(station_for):
    srv, station, client = await station_for()
    srv.device.advance(2)
    resp = await _post(client, "/api/malfunctions", {"unit": 2, "kind": "stiction", "S": 8.0, "J": 3.0, "ramp": 2.0})
    assert resp.status == 201, await resp.text()
    srv.device.advance(20)
    assert station.bank.S[1] != 8.0
    srv.device.advance(1)
    state = await (await client.get("/api/state")).json()
    assert (state["loops"][1]["S"], state["loops"][1]["J"]) == (8.0, 3.0)


async def test_operator_actions_go_through_the_register_map(station_for, client_for):
    srv, station, client = await station_for()
    modbus = await client_for(srv)
    # OP in auto: the register map's refusal, same text as over Modbus
    resp = await _post(client, "/api/loops/1", {"op": 40.0})
    assert resp.status == 409
    body = await resp.json()
    assert body["field"] == "op" and "writable only while the controller is in manual" in body["error"]
    assert (await _post(client, "/api/loops/1", {"mode": "manual"})).status == 200
    assert (await _post(client, "/api/loops/1", {"op": 40.0})).status == 200
    rr = await modbus.read_holding_registers(address_of("op_pct"), count=1, device_id=1)
    assert rr.registers == [4000]   # the accepted write shows in the register image at once
    resp = await _post(client, "/api/loops/1", {"op": 140.0})
    assert resp.status == 409 and "register op_pct: 14000 out of range 0..10000" in (await resp.json())["error"]
    resp = await _post(client, "/api/loops/2", {"sp": 1.0})
    assert resp.status == 409 and "needs an internal controller" in (await resp.json())["error"]
    srv.device.advance(1)
    assert station.bank.op[0] == pytest.approx(40.0)


@pytest.mark.parametrize(("path", "body", "status", "field"), [
    ("/api/malfunctions", {"unit": 1, "kind": "leak"}, 400, "kind"),
    ("/api/malfunctions", {"unit": 1, "kind": "stiction", "S": 250.0}, 400, "S"),
    ("/api/malfunctions", {"unit": 1, "kind": "load", "flow": 5.0, "ramp": "soon"}, 400, "ramp"),
    ("/api/malfunctions", {"unit": 7, "kind": "seize"}, 400, "unit"),
    ("/api/snapshots/nope/restore", {}, 404, "name"),
    ("/api/snapshots", {"name": "../../etc"}, 400, "name"),
    ("/api/speed", {"time_scale": -2}, 400, "time_scale"),
    ("/api/speed", {}, 400, "time_scale"),
    ("/api/loops/1", {"mode": "cascade"}, 400, "mode"),
    ("/api/loops/9", {"mode": "manual"}, 404, "unit"),
    ("/api/loops/1", {"sp": 1.0, "op": 3.0}, 400, "body"),
])
async def test_bad_input_is_a_4xx_naming_the_field_and_changes_nothing(station_for, path, body, status, field):
    srv, station, client = await station_for()
    srv.device.advance(3)
    before = (bytes(srv.device.image), srv.device.time_scale, list(station.snapshots))
    resp = await _post(client, path, body)
    assert resp.status == status
    answer = await resp.json()
    assert answer["field"] == field and field in answer["error"]
    assert (bytes(srv.device.image), srv.device.time_scale, list(station.snapshots)) == before


async def test_non_json_body_and_wrong_content_type_are_refused(station_for):
    srv, station, client = await station_for()
    resp = await client.post("/api/malfunctions", data="kind=seize", headers=JSON)
    assert resp.status == 400 and (await resp.json())["field"] == "body"
    resp = await client.post("/api/freeze", data="{}", headers={"Content-Type": "text/plain"})
    assert resp.status == 415 and srv.device.frozen is not False or srv.device.time_scale == 0


async def test_with_a_token_the_instructor_api_and_page_need_it_and_the_trainee_sees_less(station_for, caplog):
    srv, station, client = await station_for(token="s3cret-token")
    resp = await _post(client, "/api/malfunctions", {"unit": 1, "kind": "seize"})
    assert resp.status == 401 and (await resp.json())["field"] == "token"
    assert not station.bank.frozen[0]
    assert "refused POST /api/malfunctions from 127.0.0.1" in caplog.text
    assert (await client.get("/instructor", allow_redirects=False)).status == 401
    trainee = (await (await client.get("/api/state")).json())["loops"][0]
    assert "S" not in trainee and "mv" not in trainee and "score" not in trainee
    auth = {"Authorization": "Bearer s3cret-token", **JSON}
    resp = await client.post("/api/malfunctions", data=json.dumps({"unit": 1, "kind": "seize"}), headers=auth)
    assert resp.status == 201 and station.bank.frozen[0]
    resp = await client.post("/api/reveal", data=json.dumps({"unit": 1}), headers=auth)
    assert resp.status == 200
    assert "mv" in (await (await client.get("/api/state")).json())["loops"][0]
    # the page login sets the cookie, the cookie opens the instructor page
    resp = await client.get("/instructor?token=s3cret-token", allow_redirects=False)
    assert resp.status == 302
    assert (await client.get("/instructor")).status == 200


async def test_stream_sends_at_least_five_states_per_second(station_for):
    srv, station, client = await station_for(time_scale=1.0)
    resp = await client.get("/api/stream")
    assert resp.status == 200 and resp.headers["Content-Type"].startswith("text/event-stream")
    events, start = [], time.monotonic()
    while time.monotonic() - start < 1.0:
        line = await resp.content.readline()
        if line.startswith(b"data: "):
            events.append(json.loads(line[6:]))
    resp.close()
    assert len(events) >= 5
    assert events[-1]["time"] > events[0]["time"]


async def test_report_iae_equals_one_computed_from_the_recording(station_for, tmp_path):
    from valve_emulator.device.record import TickRecorder

    srv, station, client = await station_for(station_config(noise=0.02))
    dev = srv.device
    rec = TickRecorder(dev, tmp_path / "session.csv")
    await rec.start()
    dev.advance(10)
    await asyncio.sleep(0)
    assert (await _post(client, "/api/session")).status == 200
    start = station.evaluation.start
    for k in range(300):
        if k == 20:
            await _post(client, "/api/malfunctions", {"unit": 1, "kind": "load", "flow": 10.0, "ramp": 5.0})
        if k == 150:
            await _post(client, "/api/loops/1", {"mode": "manual"})
        dev.advance(1)
        await asyncio.sleep(0)
    await rec.stop()
    report = await (await client.get("/api/report")).json()
    paths = list(rec.paths.values())
    with open(paths[0]) as f:
        rows = [r for r in csv.DictReader(f) if float(r["t"]) > start + 1e-9]
    dt = 0.1
    iae = sum(abs(float(r["sp"]) - float(r["pv"])) for r in rows) * dt
    outside = sum(dt for r in rows if not -8.0 <= float(r["pv"]) <= 8.0)
    loop1 = report["loops"][0]
    assert len(rows) == report["samples"] == 300
    assert loop1["iae"] == pytest.approx(iae, rel=1e-6)
    assert loop1["time_outside"] == pytest.approx(outside, abs=1e-9)
    assert report["responses"][0]["malfunction"] == "load"
    assert report["responses"][0]["response_time"] == pytest.approx(13.0, abs=0.11)
    html = await (await client.get("/report")).text()
    assert "data:image/png;base64," in html and "FIC101" in html


async def test_alarm_limits_come_from_the_config_or_default_to_10_and_90_percent_of_the_range(station_for):
    cfg = server_from_mapping({"device": {"tick": 0.1}, "loops": [
        {"unit": 1, "name": "FIC101", "valve": {"S": 5.0, "J": 2.0}, "plant": {**PLANT, "alarms": [-2.5, 4.0]}},
        {"unit": 2, "name": "HIC102", "valve": {"S": 3.0, "J": 1.0}, "plant": PLANT},
    ]})
    srv, station, client = await station_for(cfg)
    loops = (await (await client.get("/api/state")).json())["loops"]
    assert loops[0]["limits"] == [-2.5, 4.0]
    assert loops[1]["limits"] == pytest.approx([-8.0, 8.0])      # pv_range [-10, 10]


def test_bad_alarm_limits_name_the_key():
    with pytest.raises(ConfigError, match=r"plant\.alarms must be \[lo, hi\] with lo < hi"):
        server_from_mapping({"loops": [{"unit": 1, "valve": {"S": 1.0, "J": 0.0},
                                        "plant": {**PLANT, "alarms": [4.0, -2.5]}}]})


async def test_a_comm_malfunction_acts_on_the_modbus_answers_and_clear_restores_them(station_for, client_for):
    srv, station, client = await station_for()
    modbus = await client_for(srv)
    resp = await client.post("/api/malfunctions", json={"unit": 1, "kind": "comm", "fault": 2}, headers=JSON)
    assert resp.status == 201, await resp.text()
    rr = await modbus.read_holding_registers(address_of("pv"), count=1, device_id=1)
    assert rr.isError() and rr.exception_code == 0x06                      # server device busy
    other = await modbus.read_holding_registers(address_of("pv"), count=1, device_id=2)
    assert not other.isError()                                             # only unit 1 is faulted
    assert srv.comm.state(1).words == (2, 0)                               # the unit register shows it
    resp = await client.post("/api/malfunctions", json={"unit": 1, "kind": "clear"}, headers=JSON)
    assert resp.status == 201
    rr = await modbus.read_holding_registers(address_of("pv"), count=1, device_id=1)
    assert not rr.isError() and srv.comm.state(1).words == (0, 0)


@pytest.mark.parametrize(("body", "field"), [
    ({"unit": 1, "kind": "comm"}, "fault"),
    ({"unit": 1, "kind": "comm", "fault": 9}, "fault"),
    ({"unit": 1, "kind": "comm", "fault": 1.5}, "fault"),
    ({"unit": 1, "kind": "comm", "delay_ms": 20000}, "delay_ms"),
    ({"unit": 1, "kind": "comm", "fault": 1, "ramp": 10}, "ramp"),
])
async def test_a_bad_comm_malfunction_names_the_field_and_changes_nothing(station_for, body, field):
    srv, station, client = await station_for()
    resp = await client.post("/api/malfunctions", json=body, headers=JSON)
    assert resp.status == 400 and (await resp.json())["field"] == field
    assert srv.comm.state(1).words == (0, 0)
