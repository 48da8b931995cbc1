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
    "load_loop",
    "load_server",
    "loop_from_mapping",
    "partition",
    "server_from_mapping",
    "server_slice",
]
