"""Training scenarios on the station: timed ramps, triggers on their conditions, hints, scoring rules."""

import json

import pytest
from station_helpers import JSON

pytestmark = pytest.mark.usefixtures("no_task_leak")

LESSON = """
name: sticky_valve_lesson
notes: The valve starts to stick; expect manual mode.
limits: {1: [-3, 3]}
events:
  - {at: 1.0, malfunction: {unit: 1, kind: load, flow: 2.0, ramp: 2.0}, say: "feed rises"}
triggers:
  - id: off_band
    when: {pv_outside: {unit: 1, band: [-0.5, 0.5], for: 3.0}}
    do: {hint: shape}
  - id: went_manual
    when: {manual: {unit: 1}}
    do: {say: "trainee went to manual"}
  - id: late
    when: {since_malfunction: {unit: 1, after: 30}}
    do: {malfunction: {unit: 1, kind: seize}}
  - id: acked
    when: {acknowledged: {unit: 1}}
    do: {say: "acknowledged"}
hints:
  - {id: shape, text: "Compare the shapes of OP and PV."}
scoring: {iae: 2.0, hint: 25}
"""


async def _post(client, path, body=None):
    return await client.post(path, data=json.dumps({} if body is None else body), headers=JSON)


async def test_events_ramp_and_triggers_fire_on_their_conditions(station_for):
    srv, station, client = await station_for()
    dev = srv.device
    resp = await _post(client, "/api/scenario", {"yaml": LESSON})
    assert resp.status == 200, await resp.text()
    assert (await _post(client, "/api/scenario/start")).status == 200
    t0 = station.scenario.t0
    dev.advance(11)   # the event at 1.0 s: a load ramp to 2 % over 2 s
    assert 0.0 <= station.bank.load[0] < 2.0
    dev.advance(22)   # the ramp acts from the sample at 1.0 s and ends 2 s later
    assert station.bank.load[0] == 2.0
    # PV leaves the band [-0.5, 0.5] some time after the load (dead time 10 s); the trigger waits 3 s more
    first_out = None
    for _ in range(400):
        dev.advance(1)
        if first_out is None and abs(station.bank.pv[0]) > 0.5:
            first_out = station.bank.sample_time
        if "off_band" in station.scenario.fired:
            break
    assert first_out is not None and "off_band" in station.scenario.fired
    fired_at = next(n["time"] for n in station.notes if "trigger off_band" in n["text"])
    assert fired_at - first_out == pytest.approx(3.0, abs=0.11)
    state = await (await client.get("/api/state?view=trainee")).json()
    assert state["hints"] == ["Compare the shapes of OP and PV."]
    assert "went_manual" not in station.scenario.fired
    await _post(client, "/api/loops/1", {"mode": "manual"})
    dev.advance(1)
    assert "went_manual" in station.scenario.fired
    # 30 s after the malfunction (acting from the sample at 1.0 s): the seize, acting from the sample at 31.0 s
    while station.bank.t < t0 + 1.0 + 30.0 - 0.05:     # bank.t: the time of the next sample
        assert not station.bank.frozen[0]
        dev.advance(1)
    assert station.bank.frozen[0] and "late" in station.scenario.fired
    report = await (await client.get("/api/report")).json()
    assert report["score"]["rules"]["iae"] == 2.0 and report["hints_released"]
    assert report["score"]["penalty"] == pytest.approx(2.0 * sum(lp["iae"] for lp in report["loops"])
                                                       + sum(lp["time_outside"] for lp in report["loops"])
                                                       + sum(r["response_time"] for r in report["responses"])
                                                       + sum(u["waiting"] for u in report["unanswered"]) + 25.0)


@pytest.mark.parametrize(("text", "words"), [
    ("events: [{at: -1, say: x}]", "events[0].at"),
    ("triggers: [{id: a, when: {boiling: {unit: 1}}, do: {say: x}}]", "unknown condition"),
    ("triggers: [{id: a, when: {manual: {unit: 1}}, do: {hint: nope}}]", "no hint with id 'nope'"),
    ("events: [{at: 1, malfunction: {unit: 1, kind: stiction, S: 500}}]", "events[0].malfunction.S: field 'S'"),
    ("unit: 1\nevents: [{at: 1, event: stiction, S: 500}]", "events[0].S: field 'S'"),
    ("events: [{at: 1, event: seize}]", "events[0]: which loop? the device has units [1, 2]"),
    ("events: [{at: 1, malfunction: {unit: 7, kind: seize}}]", "malfunction.unit: field 'unit': no loop at unit 7"),
    ("device: ../etc/loop.yaml", "device: the station plays a scenario on its own device"),
    ("limits: {9: [0, 1]}", "unit 9"),
    ("colour: red", "unknown key"),
])
async def test_a_bad_scenario_is_refused_naming_the_key(station_for, text, words):
    srv, station, client = await station_for()
    resp = await _post(client, "/api/scenario", {"yaml": text})
    assert resp.status == 400
    body = await resp.json()
    assert words in body["error"] and body["field"] == "scenario"
    assert station.scenario is None


async def test_the_station_plays_the_player_s_event_form_and_lines_for_the_instructor(station_for):
    srv, station, client = await station_for()
    text = ("unit: 1\nevents:\n  - {at: 0, malfunction: {kind: load, flow: 1.0}}\n  - {at: 0.5, event: seize}\n"
            "  - {at: 0.5, say: look at MV now}\n")
    assert (await _post(client, "/api/scenario", {"yaml": text})).status == 200
    assert (await _post(client, "/api/scenario/start")).status == 200
    assert station.bank.load[0] == 1.0                 # at 0 s: before the first tick of the scenario
    srv.device.advance(4)
    assert not station.bank.frozen[0]
    srv.device.advance(1)                             # tick 5 has run: the seize acts from the sample at 0.5 s
    assert station.bank.frozen[0]
    assert [n["text"] for n in station.notes[-2:]] == ["event at 0.5 s: seize on unit 1",
                                                            "event at 0.5 s: look at MV now"]
    assert station.scenario.describe()["fired"] == ["event 0", "event 1", "event 2"]
