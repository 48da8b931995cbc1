"""Hostile input on the station's HTTP API: every bad request is a 4xx JSON error naming the field, and
nothing changes (the register image, the bank, the snapshots, the speed)."""

import asyncio
import json

import pytest
import yarl
from station_helpers import JSON

from valve_emulator.device.snapshots import SnapshotStore
from valve_emulator.station import app as station_app
from valve_emulator.station.app import start_station
from valve_emulator.station.core import Station

pytestmark = pytest.mark.usefixtures("no_task_leak")

POST_ROUTES = ["/api/loops/1", "/api/alarms/1/ack", "/api/run", "/api/freeze", "/api/speed", "/api/snapshots",
               "/api/snapshots/a/restore", "/api/malfunctions", "/api/reveal", "/api/session", "/api/scenario",
               "/api/scenario/start", "/api/hints/h1/release"]


def _state(srv, station):
    """Everything a refused request must leave as it was."""
    b = srv.device.bank
    return (bytes(srv.device.image), srv.device.time_scale, sorted(s.name for s in station.snapshots),
            b.S.tolist(), b.J.tolist(), b.load.tolist(), b.noise_std.tolist(), b.frozen.tolist())


async def _refused(client, method, path, data, *, status, field, headers=JSON):
    resp = await client.request(method, path, data=data, headers=headers)
    assert resp.status == status, await resp.text()
    assert resp.content_type == "application/json"
    answer = await resp.json()
    assert answer["field"] == field, answer
    return answer


@pytest.mark.parametrize(("path", "body", "status", "field"), [
    ("/api/loops/1", {"op": 1e308}, 409, "op"),        # was a 500: no register word carries it
    ("/api/loops/1", {"op": -1e308}, 409, "op"),       # 409: refused by the register map, as over Modbus
    ("/api/loops/1", {"sp": 1e308}, 409, "sp"),
    ("/api/malfunctions", {"unit": 1, "kind": "stiction", "S": -1}, 400, "S"),   # was a 500 (clipped to 0)
    ("/api/malfunctions", {"unit": 1, "kind": "stiction", "J": 1e308}, 400, "J"),
    ("/api/malfunctions", {"unit": 1, "kind": "load", "flow": -1e308}, 400, "flow"),
    ("/api/malfunctions", {"unit": 1, "kind": "noise", "std": 1e308}, 400, "std"),
    ("/api/loops/1", {"op": "50"}, 400, "op"),
    ("/api/loops/1", {"op": True}, 400, "op"),
    ("/api/loops/1", {"mode": ["auto"]}, 400, "mode"),
    ("/api/speed", {"time_scale": None}, 400, "time_scale"),
    ("/api/reveal", {"unit": 1, "mv": "yes"}, 400, "mv"),
    ("/api/reveal", {"unit": {"a": 1}}, 400, "unit"),
    ("/api/snapshots", {"name": ["a"]}, 400, "name"),
    ("/api/scenario", {"yaml": "[" * 1200}, 400, "scenario"),   # was a 500 after seconds of parsing
    ("/api/scenario", {"yaml": "name: x\n" + "#" * 70_000}, 400, "scenario"),   # over 64 kB
])
async def test_values_of_the_wrong_type_or_beyond_any_register_are_refused_naming_the_field(
        station_for, path, body, status, field):
    srv, station, client = await station_for()
    await client.post("/api/loops/1", data=json.dumps({"mode": "manual"}), headers=JSON)
    srv.device.advance(2)
    before = _state(srv, station)
    answer = await _refused(client, "POST", path, json.dumps(body), status=status, field=field)
    assert field in answer["error"]
    assert _state(srv, station) == before


@pytest.mark.parametrize("raw", [
    b"[" * 100_000 + b"]" * 100_000,     # was a 500 (RecursionError)
    b'{"a":' * 50_000 + b"1" + b"}" * 50_000,
    b'{"op": NaN}', b'{"time_scale": Infinity}',   # Python's json takes these; JSON does not
    b"{", b"\xff\xfe{}", b"[1, 2]", b"null",
], ids=["deep-array", "deep-object", "NaN", "Infinity", "truncated", "not-utf8", "array", "null"])
async def test_malformed_json_is_refused_on_every_post_route(station_for, raw):
    srv, station, client = await station_for()
    before = _state(srv, station)
    for path in POST_ROUTES:
        answer = await _refused(client, "POST", path, raw, status=400, field="body")
        assert answer["error"].startswith("request body:")
    assert _state(srv, station) == before


async def test_unknown_paths_wrong_methods_and_large_bodies_get_json_errors(station_for):
    srv, station, client = await station_for()
    before = _state(srv, station)
    await _refused(client, "GET", "/api/nope", None, status=404, field="path")
    await _refused(client, "GET", "/nope/../../etc/passwd", None, status=404, field="path")
    await _refused(client, "POST", "/api/state", b"{}", status=405, field="method")
    big = b'{"name": "' + b"a" * (10 << 20) + b'"}'     # 10 MB
    answer = await _refused(client, "POST", "/api/snapshots", big, status=413, field="body")
    assert str(station_app.MAX_BODY) in answer["error"]
    assert _state(srv, station) == before
    assert (await client.get("/api/state")).status == 200     # and the station still answers


@pytest.mark.parametrize("name", ["..%2F..%2Fetc%2Fpasswd", "%2Fetc%2Fpasswd", "a%00b", ".hidden", "a%2Fb",
                                  "x" * 65])
async def test_path_tricks_in_snapshot_names_are_a_400_naming_the_name(station_for, tmp_path, name):
    srv, station, client = await station_for()
    outside = tmp_path / "victim.npz"
    outside.write_bytes(b"keep me")
    before = _state(srv, station)
    url = yarl.URL(f"/api/snapshots/{name}", encoded=True)
    await _refused(client, "DELETE", url, None, status=400, field="name")
    await _refused(client, "POST", yarl.URL(f"/api/snapshots/{name}/restore", encoded=True), b"{}",
                   status=400, field="name")
    await _refused(client, "POST", "/api/snapshots", json.dumps({"name": yarl.URL(name, encoded=True).path}),
                   status=400, field="name")
    assert outside.read_bytes() == b"keep me" and _state(srv, station) == before


async def test_a_wrong_token_is_compared_in_constant_time_and_changes_nothing(station_for, monkeypatch):
    compared, original = [], station_app.hmac.compare_digest

    def compare(a, b):
        compared.append(a)
        return original(a, b)

    monkeypatch.setattr(station_app.hmac, "compare_digest", compare)
    srv, station, client = await station_for(token="s3cret-token")
    before = _state(srv, station)
    wrong = ["s3cret-tokeN", "s3cret-token-and-more", "", "s3cr\u00e9t-token"]
    for given in wrong:
        headers = {"Authorization": f"Bearer {given}", **JSON}
        await _refused(client, "POST", "/api/malfunctions", json.dumps({"unit": 1, "kind": "seize"}),
                       status=401, field="token", headers=headers)
    assert _state(srv, station) == before
    assert [c.decode() for c in compared] == wrong    # every one through hmac.compare_digest


async def test_a_body_that_does_not_arrive_is_a_408_and_a_silent_connection_is_closed(monkeypatch, tmp_path):
    from station_helpers import station_config

    from valve_emulator.device.server import EmulatorServer

    monkeypatch.setattr(station_app, "BODY_TIMEOUT", 0.3)
    async with EmulatorServer(station_config(), host="127.0.0.1", port=0, time_scale=0) as srv:
        station = Station(srv.device, snapshots=SnapshotStore(tmp_path))
        runner, port = await start_station(station, host="127.0.0.1", port=0, idle_timeout=0.5)
        try:
            # headers complete, the body never comes
            r, w = await asyncio.open_connection("127.0.0.1", port)
            w.write(b"POST /api/speed HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                    b"Content-Length: 100\r\n\r\n{")
            head = await asyncio.wait_for(r.readuntil(b"\r\n\r\n"), 3)
            assert head.startswith(b"HTTP/1.1 408")
            w.write(b" " * 99)   # the rest at last: aiohttp stops reading (lingering) once the body is complete
            w.close()
            await w.wait_closed()
            # half a request line, then silence: closed after the idle timeout
            r, w = await asyncio.open_connection("127.0.0.1", port)
            w.write(b"GET /api/sta")
            assert await asyncio.wait_for(r.read(), 3) == b""
            w.close()
            await w.wait_closed()
        finally:
            await runner.cleanup()
