"""Operator-training scenarios: timelines of instructor events, parsed and checked (see :mod:`.timeline`).

The player that applies them to a device over Modbus is :mod:`valve_emulator.clients.scenario`; the command line is
``valve-emulator scenario SCENARIO.yaml``.
"""

from valve_emulator.scenario.timeline import (
    EVENT_TYPES,
    Event,
    Scenario,
    ScenarioError,
    load_scenario,
    parse_scenario,
)

__all__ = ["EVENT_TYPES", "Event", "Scenario", "ScenarioError", "load_scenario", "parse_scenario"]
