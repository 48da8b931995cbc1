"""Layer 3, stiction detectors from the literature, for comparison rows next to the project's own diagnosis.

Each detector is a pure function ``detector(op, pv, *, dt, sp=None, integrating=False) -> DetectorResult`` on
numpy arrays (no model of the plant, no I/O), with the decision thresholds fixed as published:

* ``horch`` -- cross-correlation of OP and PV, odd or even (Horch, CEP 1999): :mod:`.horch`
* ``he`` -- curve-fitting stiction index, triangle against sinusoid (He et al., IECR 2007): :mod:`.he_curve_fit`
* ``bicoherence`` -- NGI/NLI and ellipse-fitted apparent stiction (Choudhury et al., Automatica 2004; CEP 2005):
  :mod:`.bicoherence`

Each first checks that the loop oscillates regularly (:func:`~.base.oscillation`) and otherwise answers
"undetermined", since all three were published for oscillating loops.

>>> from valve_emulator.detectors import run_detectors                           # doctest: +SKIP
>>> for res in run_detectors(rec.op, rec.pv, dt=rec.dt, sp=rec.sp).values():
...     print(res.report())
"""

from __future__ import annotations

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
from valve_emulator.detectors.bicoherence import bicoherence
from valve_emulator.detectors.he_curve_fit import he_curve_fit
from valve_emulator.detectors.horch import horch

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

#: Every detector by name, in report order.
DETECTORS: Mapping[str, Detector] = types.MappingProxyType({
    "horch": horch,
    "he": he_curve_fit,
    "bicoherence": bicoherence,
})


def run_detectors(op: ArrayLike, pv: ArrayLike, *, dt: float, sp: ArrayLike | None = None,
                  integrating: bool = False, names: Iterable[str] | None = None) -> dict[str, DetectorResult]:
    """Run the named detectors (default: all of :data:`DETECTORS`) on one loop; results by name, in order."""
    chosen = list(DETECTORS) if names is None else list(names)
    unknown = [n for n in chosen if n not in DETECTORS]
    if unknown:
        raise ValueError(f"unknown detector(s) {', '.join(map(repr, unknown))}; known: {', '.join(DETECTORS)}")
    return {n: DETECTORS[n](op, pv, dt=dt, sp=sp, integrating=integrating) for n in chosen}
