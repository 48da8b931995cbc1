"""The library of candidate physics, one small module each, found and registered on import.

Every module of this package is imported once, in the order of its name, and each registers its candidate
(:func:`~valve_emulator.diagnosis.candidates.base.register`); no list of them is kept by hand. ``registry()``
lists them in that order, which is the order the search tries them in. Besides the valve and plant pieces a
nominal model may lack, the library holds the physics real data needs to be told apart from stiction:
``saturation`` (a chain limit), ``quantization`` and ``disturbance`` (after the plant, ``output`` kind) and
``tuning`` (the loop itself, ``loop`` kind). The base of each kind is in
:mod:`~valve_emulator.diagnosis.candidates.base`, with what a candidate declares.
"""

import importlib
import pkgutil

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
    TwinRole,
    get,
    register,
    registry,
)

__all__ = ["KINDS", "SLOTS", "Candidate", "ChainCandidate", "ChainContext", "DelayCandidate", "Kind",
           "LoopCandidate", "OutputCandidate", "TwinRole", "get", "register", "registry"]


def _import_every_module() -> None:
    """Import each module of this package, by name, so that each registers its candidate."""
    for name in sorted(m.name for m in pkgutil.iter_modules(__path__)):
        importlib.import_module(f"{__name__}.{name}")


_import_every_module()
