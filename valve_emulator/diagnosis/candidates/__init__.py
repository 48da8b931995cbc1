"""The library of candidate physics, one small module each, registered by name on import.

``registry()`` lists them in the order below; issue 7 adds modules here the same way.
"""

from valve_emulator.diagnosis.candidates import (  # noqa: F401  (imported for registration)
    actuator_lag,
    characteristic,
    dead_time,
    deadband,
    stiction,
)
from valve_emulator.diagnosis.candidates.base import SLOTS, Candidate, ChainContext, get, register, registry

__all__ = ["SLOTS", "Candidate", "ChainContext", "get", "register", "registry"]
