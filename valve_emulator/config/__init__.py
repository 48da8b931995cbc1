"""Configuration layer: YAML files -> validated, frozen dataclasses (see ``docs/config.md``).

Downstream code takes these typed objects, never dicts; use ``dataclasses.replace`` for overrides (the
result is validated again).
"""

from valve_emulator.config.layout import Slice, partition, server_slice
from valve_emulator.config.loader import load_loop, load_server, loop_from_mapping, server_from_mapping
from valve_emulator.config.schema import (
    ConfigError,
    ControllerConfig,
    DeviceConfig,
    DisturbanceConfig,
    LoopConfig,
    PlantConfig,
    ServerConfig,
    SimulationConfig,
    ValveConfig,
)
from valve_emulator.config.writer import dump_loop, loop_to_mapping, write_loop

__all__ = [
    "ConfigError",
    "ControllerConfig",
    "DeviceConfig",
    "DisturbanceConfig",
    "LoopConfig",
    "PlantConfig",
    "ServerConfig",
    "SimulationConfig",
    "Slice",
    "ValveConfig",
    "dump_loop",
    "load_loop",
    "loop_to_mapping",
    "load_server",
    "loop_from_mapping",
    "partition",
    "server_from_mapping",
    "server_slice",
    "write_loop",
]
