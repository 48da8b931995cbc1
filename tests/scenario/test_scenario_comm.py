"""Communication faults as scenario events: parsed and checked like every event, a duration adds the event
that ends the fault, and over Modbus the player writes the unit registers at their addresses and refuses an
event it could not carry out during an outage."""

import textwrap

import pytest

from valve_emulator.device.registers import COMM_BASE
from valve_emulator.scenario import ScenarioError, check_registers_carry, parse_scenario, register_writes
from valve_emulator.scenario.player import write_groups

DEVICE = """\
device:
  plant: {num: [1.0], den: [1.0, 0.0], pv_range: [-10.0, 10.0]}
  device: {unit: 3, tick: 0.1}
duration: 100
"""


def scenario(events: str):
    return parse_scenario(DEVICE + "events:\n" + textwrap.indent(textwrap.dedent(events), "  "), source="s.yaml")


def test_a_30_s_outage_is_set_and_cleared():
    sc = scenario("""\
        - {at: 10, event: comm, fault: bad_crc, delay_ms: 250, duration: 30}
        - {at: 20, event: seize}
        - {at: 50, event: comm, fault: no_response, duration: 30}
        """)
    assert [(ev.at, ev.kind, register_writes(ev, sc)) for ev in sc.events] == [
        (10.0, "comm", [("comm_fault", 5), ("comm_delay_ms", 250)]),
        (20.0, "seize", [("fault", 1)]),                   # a slow link still carries the write out
        (40.0, "comm", [("comm_fault", 0), ("comm_delay_ms", 0)]),
        (50.0, "comm", [("comm_fault", 1), ("comm_delay_ms", 0)]),
        (80.0, "comm", [("comm_fault", 0), ("comm_delay_ms", 0)]),
    ]
    assert sc.events[2].say == "end of the communication fault of line 6"
    check_registers_carry(sc)
    assert write_groups(register_writes(sc.events[0], sc)) == [(COMM_BASE, [5, 250])]   # one request to 0xFF00


@pytest.mark.parametrize(("events", "message"), [
    ("- {at: 10, event: comm, fault: 6}", r"s.yaml:6: events\[0\].fault: field 'fault' must be a whole number 0..5 "),
    ("- {at: 10, event: comm, fault: jam}", r"events\[0\].fault: field 'fault' must be 0..5 or one of none, no_resp"),
    ("- {at: 10, event: comm, fault: busy, delay_ms: 20000}", r"'delay_ms' must be a whole number 0..10000"),
    ("- {at: 10, malfunction: {kind: comm, fault: busy, delay_ms: 0.5}}", r"malfunction.delay_ms: .* got 0.5"),
    ("- {at: 10, event: comm, fault: busy, duration: 0}", r"events\[0\].duration: must be > 0 s"),
    ("- {at: 90, event: comm, fault: close, duration: 30}", r"ends at 120 s, after the end of the scenario"),
    ("- {at: 10, event: comm}", r"a comm event needs 'fault'"),
])
def test_bad_comm_events_name_the_line(events, message):
    with pytest.raises(ScenarioError, match=message):
        scenario(events)


def test_over_modbus_an_event_inside_an_outage_is_refused_naming_both_lines():
    """The unit carries out no write during a no_response, busy, failure or close fault; on a device in this
    process the same timeline plays (the engine injects, it does not write over Modbus)."""
    sc = scenario("- {at: 10, event: comm, fault: busy, duration: 30}\n- {at: 20, event: seize}")
    with pytest.raises(ScenarioError, match=r"s.yaml:7: a seize event at 20 s falls inside the communication "
                                            r"fault set at 10 s \(line 6\)"):
        check_registers_carry(sc)
    assert [ev.kind for ev in sc.events] == ["comm", "seize", "comm"]
