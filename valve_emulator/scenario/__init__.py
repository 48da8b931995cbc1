"""Scenarios: timed faults, set points and lines for the instructor, one file format and one engine.

- :mod:`~valve_emulator.scenario.timeline`: the scenario file, parsed and checked before anything runs. Its
  faults are the device's malfunctions (:data:`valve_emulator.device.malfunctions.KINDS`); the instructor
  station adds triggers, hints, limits and scoring in the same file.
- :mod:`~valve_emulator.scenario.player`: the engine -- due ticks, applying events on a device in this process
  or over its registers, the check of a device attached over Modbus.

Played by ``valve-emulator scenario SCENARIO.yaml`` (:mod:`valve_emulator.clients.scenario`) and by the
station (:mod:`valve_emulator.station.scenario_run`); the format is in docs/scenarios.md.
"""

from valve_emulator.scenario._yaml import ScenarioError
from valve_emulator.scenario.player import (
    Applied,
    Clock,
    DeviceMismatch,
    DevicePlayer,
    RegisterChannel,
    Timeline,
    WriteRefused,
    check_registers_carry,
    due_ticks,
    follow,
    play,
    play_on_device,
    probe,
    register_writes,
)
from valve_emulator.scenario.timeline import (
    EVENT_KINDS,
    Condition,
    DeviceShape,
    Event,
    Hint,
    RegisterWrite,
    Say,
    Scenario,
    SetPoint,
    Trigger,
    load_scenario,
    parse_scenario,
)

__all__ = [
    "EVENT_KINDS",
    "Applied",
    "Clock",
    "Condition",
    "DeviceMismatch",
    "DevicePlayer",
    "DeviceShape",
    "Event",
    "Hint",
    "RegisterChannel",
    "RegisterWrite",
    "Say",
    "Scenario",
    "ScenarioError",
    "SetPoint",
    "Timeline",
    "Trigger",
    "WriteRefused",
    "check_registers_carry",
    "due_ticks",
    "follow",
    "load_scenario",
    "parse_scenario",
    "play",
    "play_on_device",
    "probe",
    "register_writes",
]
