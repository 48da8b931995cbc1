"""The station's requests have roles of the permission table: the token is the instructor, users of a users file
sign in with HTTP Basic and act as their role (viewer, operator, instructor, a custom role), and operator actions
go through Device.write under that role."""

import base64
import json
import logging

import pytest
from station_helpers import JSON

from valve_emulator.device.accounts import hash_password, load_users
from valve_emulator.device.roles import RoleTable

PASSWORDS = {"vera": ("viewer", "look"), "otto": ("operator", "run"), "ines": ("instructor", "teach"),
             "sid": ("setter", "set")}
TABLE = RoleTable.of([("setter", ("sp",))])   # a custom role: writes the set point only


@pytest.fixture(scope="module")
def users(tmp_path_factory):
    path = tmp_path_factory.mktemp("station-users") / "users.yaml"
    path.write_text("users:\n" + "".join(f"  {n}: {{role: {r}, password: '{hash_password(pw, iterations=1000)}'}}\n"
                                         for n, (r, pw) in PASSWORDS.items()))
    return load_users(path, TABLE)


def _as(user, password=None):
    password = PASSWORDS[user][1] if password is None else password
    return {"Authorization": "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode(), **JSON}


async def _post(client, path, body, headers=JSON):
    resp = await client.post(path, data=json.dumps(body), headers=headers)
    return resp.status, await resp.json()


#: (user, body of POST /api/loops/1) -> HTTP status: the role decides, the register map checks the value
OPERATE = [
    ("vera", {"sp": 2.0}, 403), ("vera", {"mode": "manual"}, 403),
    ("otto", {"sp": 2.0}, 200), ("otto", {"mode": "manual"}, 200),
    ("sid", {"sp": 2.0}, 200), ("sid", {"mode": "manual"}, 403),
    ("ines", {"sp": 2.0}, 200), ("ines", {"mode": "manual"}, 200),
]


@pytest.mark.parametrize(("user", "body", "status"), OPERATE)
async def test_operator_actions_are_allowed_by_the_users_role(station_for, users, user, body, status):
    srv, station, client = await station_for(users=users)
    before = (float(station.bank._sp[0]), bool(station.bank.auto[0]))
    got, answer = await _post(client, "/api/loops/1", body, _as(user))
    assert got == status, answer
    srv.device.advance(1)
    after = (float(station.bank._sp[0]), bool(station.bank.auto[0]))
    assert (after != before) == (status == 200)
    if status == 403:
        assert answer["field"] in (*body, "role") and PASSWORDS[user][0] in answer["error"]


async def test_only_an_instructor_user_uses_the_instructor_controls_and_page(station_for, users):
    srv, station, client = await station_for(users=users)
    for user in ("vera", "otto", "sid"):
        assert (await _post(client, "/api/freeze", {}, _as(user)))[0] == 403
        assert (await client.get("/instructor", headers=_as(user))).status == 403
    assert (await _post(client, "/api/freeze", {}, _as("ines")))[0] == 200
    assert (await client.get("/instructor", headers=_as("ines"))).status == 200
    state = await (await client.get("/api/state", headers=_as("ines"))).json()
    assert "S" in state["loops"][0]   # the instructor's view


async def test_with_users_anonymous_visitors_watch_and_are_asked_to_sign_in(station_for, users):
    srv, station, client = await station_for(users=users)
    assert (await client.get("/api/state")).status == 200
    resp = await client.post("/api/loops/1", data=json.dumps({"sp": 2.0}), headers=JSON)
    assert resp.status == 401 and resp.headers["WWW-Authenticate"].startswith("Basic realm=")
    assert (await _post(client, "/api/alarms/1/ack", {}))[0] == 401
    assert (await _post(client, "/api/alarms/1/ack", {}, _as("vera")))[0] == 403   # a viewer does not acknowledge
    assert (await _post(client, "/api/alarms/1/ack", {}, _as("otto")))[0] == 200


@pytest.mark.parametrize("headers", [_as("otto", "wrong"), _as("nobody", "run"),
                                     {"Authorization": "Basic not-base64!", **JSON}])
async def test_wrong_credentials_are_401_and_change_nothing(station_for, users, headers):
    srv, station, client = await station_for(users=users)
    status, answer = await _post(client, "/api/loops/1", {"sp": 2.0}, headers)
    assert status == 401 and answer["field"] == "credentials"
    srv.device.advance(1)
    assert float(station.bank._sp[0]) == 0.0


async def test_the_station_token_is_the_instructor_and_without_users_the_trainee_operates(station_for):
    srv, station, client = await station_for(token="s3cret-token")
    assert (await _post(client, "/api/loops/1", {"sp": 2.0}))[0] == 200          # anonymous: operator
    assert (await _post(client, "/api/freeze", {}))[0] == 401
    bearer = {"Authorization": "Bearer s3cret-token", **JSON}
    assert (await _post(client, "/api/freeze", {}, bearer))[0] == 200
    wrong = {"Authorization": "Bearer wrong-token!", **JSON}
    assert (await _post(client, "/api/run", {}, wrong))[0] == 401


async def test_a_flood_of_refused_actions_is_logged_once_per_interval(station_for, users, caplog):
    caplog.set_level(logging.WARNING, logger="valve_emulator.station")
    srv, station, client = await station_for(users=users)
    for _ in range(200):
        assert (await _post(client, "/api/loops/1", {"sp": 2.0}, _as("vera")))[0] == 403
    lines = [r.getMessage() for r in caplog.records if r.name == "valve_emulator.station"]
    assert len(lines) == 1
    assert "127.0.0.1 (user 'vera')" in lines[0] and "role 'viewer'" in lines[0]


def test_serve_refuses_a_station_users_file_with_a_role_outside_the_table(tmp_path, capsys):
    from valve_emulator.cli import main

    bad = tmp_path / "users.yaml"
    bad.write_text(f"users:\n  sid: {{role: setter, password: '{hash_password('set', iterations=1000)}'}}\n")
    assert main(["serve", "--port", "0", "--web", "0", "--web-users", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "users.sid.role" in err and "viewer, operator, instructor" in err
    assert main(["serve", "--port", "0", "--web-users", str(bad)]) == 2
    assert "--web-users and --snapshots need --web PORT" in capsys.readouterr().err
