"""Public entry point for the stiction models: ``valve_emulator.stiction.simulate(op, S=, J=)``.

The implementation lives in :mod:`valve_emulator.physics.stiction`; this module re-exports its public API.
"""

from valve_emulator.physics.stiction import (
    DEFAULT_MODEL,
    MODELS,
    StictionBank,
    Valve,
    rest_samples_for,
    seed_to_2005,
    simulate,
    simulate_many,
    validate_parameters,
)

__all__ = [
    "DEFAULT_MODEL",
    "MODELS",
    "StictionBank",
    "Valve",
    "rest_samples_for",
    "seed_to_2005",
    "simulate",
    "simulate_many",
    "validate_parameters",
]
