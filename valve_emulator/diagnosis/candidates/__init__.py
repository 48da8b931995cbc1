"""The library of candidate physics, one small module each, registered by name on import.

``registry()`` lists them in the order below: the valve and plant pieces of issue 6, then the physics real
data needs to be told apart from stiction (issue 7): ``saturation`` (a chain limit), ``quantization`` and
``disturbance`` (after the plant, ``output`` kind) and ``tuning`` (the loop itself, ``loop`` kind).
"""

from valve_emulator.diagnosis.candidates import (  # noqa: F401  (imported for registration)
    actuator_lag,
    characteristic,
    dead_time,
    deadband,
    disturbance,
    quantization,
    saturation,
    stiction,
    tuning,
)
from valve_emulator.diagnosis.candidates.base import (KINDS, SLOTS, Candidate, ChainContext, get, register,
                                                      registry)

__all__ = ["KINDS", "SLOTS", "Candidate", "ChainContext", "get", "register", "registry"]
