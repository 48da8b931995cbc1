"""Scenario files: the schema, the register words each event writes, and bad input rejected with its line
before anything starts."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from valve_emulator.cli import main as cli_main
from valve_emulator.device.malfunctions import Kind
from valve_emulator.device.registers import Scaling, address_of, decode_write
from valve_emulator.device.roles import INSTRUCTOR
from valve_emulator.scenario import (
    EVENT_KINDS,
    ScenarioError,
    check_registers_carry,
    load_scenario,
    parse_scenario,
    register_writes,
)

SCENARIOS = Path(__file__).resolve().parents[2] / "configs" / "scenarios"

DEVICE = """\
device:
  valve: {S: 5.0, J: 2.0}
  plant: {num: [1.0], den: [1.0, 0.0], pv_range: [-10.0, 10.0], noise: 0.5}
  controller: {kc: 0.4, ti: 2.0}
  device: {unit: 3, tick: 0.1}
duration: 100
"""


def scenario(events: str, device: str = DEVICE):
    return parse_scenario(device + "events:\n" + textwrap.indent(textwrap.dedent(events), "  "),
                          source="s.yaml")


def test_each_old_event_type_is_the_malfunction_or_register_write_it_always_was():
    sc = scenario("""\
        - {at: 0, event: stiction, S: 3.5, J: 1.25}
        - {at: 1, event: load, flow: -2.5}
        - {at: 2, event: noise, std: 1.5}
        - {at: 3, event: seize}
        - {at: 4, event: release}
        - {at: 5, event: sp, value: 5.0}
        - {at: 6, event: normal, say: back to normal}
        - {at: 7, event: write, register: kc, value: 0.25}
        - {at: 8, event: comm, fault: busy, delay_ms: 40}
        """)
    assert sc.unit == 3 and sc.dt == 0.1 and sc.loop.controller is not None
    assert [ev.describe() for ev in sc.events] == [
        "stiction S=3.5 J=1.25", "load flow=-2.5",
        "noise std=0.3",                                   # 1.5 % of the range -10..10, now in PV units
        "seize", "release", "sp value=5", "clear", "write register=kc value=0.25", "comm fault=2 delay_ms=40"]
    # over Modbus they write what the old player wrote (clear also ends a communication fault)
    assert [register_writes(ev, sc) for ev in sc.events] == [
        [("S", 350), ("J", 125)],
        [("load", (-250) & 0xFFFF)],
        [("noise", 150)],
        [("fault", 1)],
        [("fault", 0)],
        [("sp", 7500)],                                    # 5.0 on -10..10 is 75 % of the range
        [("S", 500), ("J", 200), ("load", 0), ("noise", 250), ("fault", 0), ("comm_fault", 0),
         ("comm_delay_ms", 0)],                            # noise 0.5 = 2.5 % of 20
        [("kc", 250)],
        [("comm_fault", 2), ("comm_delay_ms", 40)],
    ]
    assert sc.events[6].say == "back to normal"
    assert (sc.tick_of(0.24), sc.tick_of(0.26)) == (2, 3)   # the nearest tick
    assert sc.tick_of(60.0) == 600


def test_the_old_event_form_and_the_malfunction_form_parse_to_the_same_faults():
    old = scenario("""\
        - {at: 1, event: stiction, S: 3.5, J: 1.25}
        - {at: 2, event: noise, std: 1.5}
        - {at: 3, event: normal}
        - {at: 4, event: comm, fault: bad_crc, duration: 2}
        """)
    new = scenario("""\
        - {at: 1, malfunction: {kind: stiction, S: 3.5, J: 1.25}}
        - {at: 2, malfunction: {kind: noise, std: 0.3}}
        - {at: 3, malfunction: {kind: clear}}
        - {at: 4, malfunction: {kind: comm, fault: 5, delay_ms: 0}}
        - {at: 6, malfunction: {unit: 3, kind: comm, fault: 0, delay_ms: 0}}
        """)
    assert [(ev.at, ev.action) for ev in old.events] == [(ev.at, ev.action) for ev in new.events]


def test_every_fault_kind_is_a_scenario_event_in_both_forms():
    for kind in Kind:
        params = {"stiction": ", S: 1.0", "load": ", flow: 1.0", "noise": ", std: 0.1", "sensor_drift": ", bias: 0.5",
                  "comm": ", fault: 0"}.get(kind.value, "")
        old = scenario(f"- {{at: 1, event: {kind.value}{params}}}\n")
        new = scenario(f"- {{at: 1, malfunction: {{kind: {kind.value}{params}}}}}\n")
        assert old.events[0].kind == new.events[0].kind == kind.value
    assert set(EVENT_KINDS) == {k.value for k in Kind} | {"normal", "sp", "write"}


def test_the_words_are_what_the_device_decodes_back():
    sc = scenario("- {at: 1, event: load, flow: -2.5}\n- {at: 2, event: noise, std: 1.5}\n")
    scaling = Scaling.from_config(sc.config)
    (name, raw), = register_writes(sc.events[0], sc)
    assert decode_write(address_of(name), [raw], scaling, 0, role=INSTRUCTOR) == [("load", -2.5)]
    (name, raw), = register_writes(sc.events[1], sc)
    assert decode_write(address_of(name), [raw], scaling, 0, role=INSTRUCTOR) == [("noise", pytest.approx(0.3))]


def test_ramps_and_sensor_faults_are_refused_over_modbus_naming_the_line():
    sc = scenario("- {at: 1, event: seize}\n- {at: 2, malfunction: {kind: load, flow: 2.0, ramp: 10}}\n")
    with pytest.raises(ScenarioError, match=r"^s\.yaml:9: load flow=2 ramp=10: the device's registers carry no "
                                            r"ramps .* \(without --attach\)"):
        check_registers_carry(sc)
    with pytest.raises(ScenarioError, match=r"^s\.yaml:8: sensor_drift bias=1: the device's registers"):
        check_registers_carry(scenario("- {at: 1, malfunction: {kind: sensor_drift, bias: 1.0}}\n"))
    check_registers_carry(scenario("- {at: 1, malfunction: {kind: load, flow: 2.0}}\n"))


@pytest.mark.parametrize("events, line, message", [
    ("- {at: 1, event: stiction, S: 2}\n- {at: 2, event: explode}\n", 9, "unknown event type 'explode'"),
    ("- {at: 5, event: seize}\n- {at: 4, event: release}\n", 9, r"time goes backwards: 4 s after 5 s \(line 8\)"),
    ("- {at: 1, event: write, register: valve_gain, value: 3}\n", 8, "the device has no register 'valve_gain'"),
    ("- {at: 1, event: write, register: mv_pct, value: 3}\n", 8, "register mv_pct .* is read-only"),
    ("- {at: 1, event: stiction, S: 2, Q: 1}\n", 8, r"events\[0\]\.Q: field 'Q' is not a parameter of stiction"),
    ("- {at: 1, event: stiction}\n", 8, "stiction needs field 'S' or 'J'"),
    ("- {at: 1, event: load}\n", 8, r"events\[0\]\.flow: field 'flow' is required for load"),
    ("- {at: 1, event: normal, S: 1}\n", 8, r"events\[0\]\.S: unknown key for a normal event"),
    ("- {at: 1, malfunction: {kind: warp}}\n", 8, r"events\[0\]\.malfunction\.kind: .*unknown malfunction 'warp'"),
    ("- {at: 1, malfunction: {kind: noise, std: 50}}\n", 8, r"malfunction\.std: .*register noise: 25000 out of"),
    ("- {at: 1, malfunction: {kind: seize, unit: 4}}\n", 8, r"malfunction\.unit: field 'unit': no loop at unit 4"),
    ("- {at: 1, sp: 1.0, malfunction: {kind: seize}}\n", 8, r"events\[0\]: needs exactly one of malfunction"),
    ("- {at: 1, hint: look}\n", 8, r"events\[0\]\.hint: no hint with id 'look'"),
    ("- {at: 1, event: load, flow: 200}\n", 8, "register load: 20000 out of range -10000..10000"),
    ("- {at: 1, event: sp, value: 50}\n", 8, "register sp: 30000 out of range 0..10000"),
    ("- {at: -1, event: seize}\n", 8, r"events\[0\]\.at: must be >= 0"),
    ("- {at: 101, event: seize}\n", 8, "after the end of the scenario"),
    ("- {at: 1, event: noise, std: fast}\n", 8, r"events\[0\]\.std: field 'std' must be a finite number"),
])
def test_bad_events_are_rejected_naming_the_line(events, line, message):
    with pytest.raises(ScenarioError, match=rf"^s\.yaml:{line}: .*{message}"):
        scenario(events)


def test_a_set_point_on_a_loop_without_internal_controller_is_refused():
    device = DEVICE.replace("  controller: {kc: 0.4, ti: 2.0}\n", "")
    with pytest.raises(ScenarioError, match=r"^s\.yaml:7: .*register sp .* needs an internal controller"):
        scenario("- {at: 1, event: sp, value: 1.0}\n", device)


@pytest.mark.parametrize("text, message", [
    ("duration: 10\nevents: []\n", r"^s\.yaml:1: missing key 'device'"),
    (DEVICE + "events: []\nspeed: 3\n", r"^s\.yaml:8: speed: unknown key"),
    (DEVICE + "unit: 4\nevents: []\n", r"^s\.yaml:7: unit: the device has no loop on unit 4"),
    (DEVICE.replace("tick: 0.1", "tick: -1") + "events: []\n", r"^s\.yaml:1: device: .*tick must be > 0"),
    (DEVICE + "events:\n  - {at: 1, event: seize}\n  - {at: 1, event: seize, at: 2}\n", r"^s\.yaml:9: duplicate key"),
    (DEVICE + "events: [\n", r"^s\.yaml:\d+: YAML syntax error"),
])
def test_bad_files_are_rejected_naming_the_line(text, message):
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(text, source="s.yaml")


def test_device_may_be_a_config_file_relative_to_the_scenario(tmp_path):
    (tmp_path / "loops").mkdir()
    (tmp_path / "loops" / "lvl.yaml").write_text(
        "plant: {num: [1.0], den: [1.0, 0.0]}\ncontroller: {kc: 0.4, ti: 2.0}\n")
    path = tmp_path / "s.yaml"
    path.write_text("device: loops/lvl.yaml\nduration: 10\nevents:\n  - {at: 1, event: sp, value: 2.0}\n")
    assert load_scenario(path).loop.name == "lvl"
    path.write_text("device: loops/missing.yaml\nduration: 10\nevents: []\n")
    with pytest.raises(ScenarioError, match=rf"^{path}:1: device: .*missing\.yaml.*cannot read"):
        load_scenario(path)


@pytest.mark.parametrize("path", sorted(SCENARIOS.glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_scenarios_load_and_say_what_to_conclude(path):
    sc = load_scenario(path)
    assert len(sc.events) >= 3 and sc.duration >= sc.events[-1].at
    assert "should see" in sc.description and "conclude" in sc.description


def test_at_least_three_shipped_scenarios_cover_every_fault():
    kinds = {ev.kind for p in SCENARIOS.glob("*.yaml") for ev in load_scenario(p).events}
    assert len(list(SCENARIOS.glob("*.yaml"))) >= 3
    assert {"stiction", "load", "noise", "seize", "release", "sp", "clear"} <= kinds


def test_cli_rejects_a_bad_scenario_before_starting_anything(tmp_path, monkeypatch, capsys):
    from valve_emulator.device.server import EmulatorServer

    started = []
    monkeypatch.setattr(EmulatorServer, "start", lambda self: started.append(self))
    bad = tmp_path / "bad.yaml"
    bad.write_text(DEVICE + "events:\n  - {at: 1, event: seize}\n  - {at: 2, event: meltdown}\n")
    assert cli_main(["scenario", str(bad), "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:9: events[1].event: unknown event type 'meltdown'" in err
    assert started == []


def test_cli_check_lists_the_events(capsys):
    assert cli_main(["scenario", str(SCENARIOS / "overshoot_after_maintenance.yaml"), "--check"]) == 0
    out = capsys.readouterr().out
    assert "seize" in out and "stiction S=3 J=4.5" in out and "should see" in out
