"""Communication faults as scenario events: parsed and checked like every event, a duration adds the event
that ends the fault, and the player writes the unit registers at their addresses."""

import textwrap

import pytest

from valve_emulator.device.registers import COMM_BASE
from valve_emulator.scenario import ScenarioError, parse_scenario
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
    assert [(ev.at, ev.kind, ev.writes) for ev in sc.events] == [
        (10.0, "comm", (("comm_fault", 5), ("comm_delay_ms", 250))),
        (20.0, "seize", (("fault", 1),)),                   # a slow link still carries the write out
        (40.0, "comm", (("comm_fault", 0), ("comm_delay_ms", 0))),
        (50.0, "comm", (("comm_fault", 1), ("comm_delay_ms", 0))),
        (80.0, "comm", (("comm_fault", 0), ("comm_delay_ms", 0))),
    ]
    assert write_groups(sc.events[0].writes) == [(COMM_BASE, [5, 250])]   # one request to 0xFF00


@pytest.mark.parametrize(("events", "message"), [
    ("- {at: 10, event: comm, fault: 6}", r"s.yaml:\d+: events\[0\].fault: must be 0..5 or one of none, "),
    ("- {at: 10, event: comm, fault: jam}", r"events\[0\].fault: must be 0..5"),
    ("- {at: 10, event: comm, fault: busy, delay_ms: 20000}", r"register comm_delay_ms: 20000 out of range"),
    ("- {at: 10, event: comm, fault: busy, duration: 0}", r"events\[0\].duration: must be > 0 s"),
    ("- {at: 90, event: comm, fault: close, duration: 30}", r"ends at 120 s, after the end of the scenario"),
    ("- {at: 10, event: comm}", r"a comm event needs 'fault'"),
    ("- {at: 10, event: comm, fault: busy, duration: 30}\n- {at: 20, event: seize}",
     r"s.yaml:7: a seize event at 20 s falls inside the communication fault set at 10 s \(line 6\)"),
])
def test_bad_comm_events_name_the_line(events, message):
    with pytest.raises(ScenarioError, match=message):
        scenario(events)
