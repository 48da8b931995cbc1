"""The library of candidate physics, one small module each, registered by name on import.

``registry()`` lists them in the order below: the valve and plant pieces a nominal model may lack, then the
physics real data needs to be told apart from stiction: ``saturation`` (a chain limit), ``quantization`` and
``disturbance`` (after the plant, ``output`` kind) and ``tuning`` (the loop itself, ``loop`` kind). The base
of each kind is in :mod:`~valve_emulator.diagnosis.candidates.base`.
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
from valve_emulator.diagnosis.candidates.base import (
    KINDS,
    SLOTS,
    Candidate,
    ChainCandidate,
    ChainContext,
    DelayCandidate,
    Kind,
    LoopCandidate,
    OutputCandidate,
    get,
    register,
    registry,
)

__all__ = ["KINDS", "SLOTS", "Candidate", "ChainCandidate", "ChainContext", "DelayCandidate", "Kind",
           "LoopCandidate", "OutputCandidate", "get", "register", "registry"]
