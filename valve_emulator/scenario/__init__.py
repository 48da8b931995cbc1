"""Operator-training scenarios: timelines of instructor events and the engine that plays them.

- :mod:`~valve_emulator.scenario.timeline`: the scenario file, parsed and checked before anything runs.
- :mod:`~valve_emulator.scenario.player`: the engine -- due ticks, the check of the device, applying events --
  against an abstract register channel and clock.

The Modbus front end is :mod:`valve_emulator.clients.scenario`; the command line is
``valve-emulator scenario SCENARIO.yaml``.
"""

from valve_emulator.scenario.player import (
    Applied,
    Clock,
    DeviceClock,
    DeviceMismatch,
    RegisterChannel,
    WriteRefused,
    due_ticks,
    play,
    probe,
)
from valve_emulator.scenario.timeline import (
    EVENT_TYPES,
    Event,
    Scenario,
    ScenarioError,
    load_scenario,
    parse_scenario,
)

__all__ = [
    "EVENT_TYPES",
    "Applied",
    "Clock",
    "DeviceClock",
    "DeviceMismatch",
    "Event",
    "RegisterChannel",
    "Scenario",
    "ScenarioError",
    "WriteRefused",
    "due_ticks",
    "load_scenario",
    "parse_scenario",
    "play",
    "probe",
]
