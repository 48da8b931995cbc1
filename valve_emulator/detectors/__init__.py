"""Layer 3, stiction detectors from the literature, for comparison rows next to the project's own diagnosis.

Each detector is a pure function ``detector(op, pv, *, dt, sp=None, integrating=False) -> DetectorResult`` on
numpy arrays (no model of the plant, no I/O), with the decision thresholds fixed as published:

* ``horch`` -- cross-correlation of OP and PV, odd or even (Horch, CEP 1999): :mod:`.horch`
* ``he`` -- curve-fitting stiction index, triangle against sinusoid (He et al., IECR 2007): :mod:`.he_curve_fit`
* ``bicoherence`` -- NGI/NLI and ellipse-fitted apparent stiction (Choudhury et al., Automatica 2004; CEP 2005):
  :mod:`.bicoherence`

Each first checks that the loop oscillates regularly (:func:`~.base.oscillation`) and otherwise answers
"undetermined", since all three were published for oscillating loops.

The three detectors (and :mod:`scipy.signal` and :mod:`scipy.stats`, which they need: ~0.6 s to import) are
loaded on first use of :data:`DETECTORS`, :func:`run_detectors` or a detector's name here: the diagnosis imports
only the oscillation test of :mod:`.base`, and a first ``diagnose`` should not wait for the rest.

>>> from valve_emulator.detectors import run_detectors                           # doctest: +SKIP
>>> for res in run_detectors(rec.op, rec.pv, dt=rec.dt, sp=rec.sp).values():
...     print(res.report())
"""

from __future__ import annotations

import functools
import types
from collections.abc import Callable, Iterable, Mapping

from numpy.typing import ArrayLike

from valve_emulator.detectors.base import (
    DECISIONS,
    NO_STICTION,
    NOT_APPLICABLE,
    STICTION,
    UNDETERMINED,
    Decision,
    DetectorResult,
    Oscillation,
    oscillation,
)

__all__ = [
    "DETECTORS",
    "Decision",
    "DECISIONS",
    "STICTION",
    "NO_STICTION",
    "UNDETERMINED",
    "NOT_APPLICABLE",
    "DetectorResult",
    "Detector",
    "Oscillation",
    "oscillation",
    "horch",
    "he_curve_fit",
    "bicoherence",
    "run_detectors",
]

Detector = Callable[..., DetectorResult]


@functools.cache
def _detectors() -> Mapping[str, Detector]:
    """Every detector by name, in report order (:data:`DETECTORS`), imported on the first call.

    Importing a detector's module binds the package's attribute of that name to the module; the functions are
    bound again here, so that ``valve_emulator.detectors.horch`` stays the function, as the eager import had it."""
    from valve_emulator.detectors.bicoherence import bicoherence
    from valve_emulator.detectors.he_curve_fit import he_curve_fit
    from valve_emulator.detectors.horch import horch

    globals().update(horch=horch, he_curve_fit=he_curve_fit, bicoherence=bicoherence)
    return types.MappingProxyType({"horch": horch, "he": he_curve_fit, "bicoherence": bicoherence})


def __getattr__(name: str):
    """``DETECTORS`` (every detector by name, in report order) and the detector functions, on first use."""
    if name == "DETECTORS":
        return _detectors()
    if name in ("horch", "he_curve_fit", "bicoherence"):
        _detectors()
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def run_detectors(op: ArrayLike, pv: ArrayLike, *, dt: float, sp: ArrayLike | None = None,
                  integrating: bool = False, names: Iterable[str] | None = None) -> dict[str, DetectorResult]:
    """Run the named detectors (default: all of :data:`DETECTORS`) on one loop; results by name, in order."""
    detectors = _detectors()
    chosen = list(detectors) if names is None else list(names)
    unknown = [n for n in chosen if n not in detectors]
    if unknown:
        raise ValueError(f"unknown detector(s) {', '.join(map(repr, unknown))}; known: {', '.join(detectors)}")
    return {n: detectors[n](op, pv, dt=dt, sp=sp, integrating=integrating) for n in chosen}
