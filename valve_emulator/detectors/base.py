"""What every comparison detector shares: the result object, input checks and the oscillation test.

Oscillation test
----------------
The methods compared here were published for *oscillating* loops, so each first asks whether the loop
oscillates, with the regularity test of Thornhill, Huang & Zhang ("Detection of multiple oscillations in
control loops", J. Process Control 13 (2003) 91–100): the zero crossings ``z_1 < z_2 < …`` of the
autocorrelation function of the (linearly detrended) signal give full-period estimates
``T_i = z_{i+2} − z_i``, and the oscillation is regular when

.. math::  r = \\frac{\\bar T}{3\\,\\sigma_T} > 1 .

Crossings are looked for up to lag ``0.75 N`` and at least two period estimates are required; both are this
project's choices (the paper does not fix them), made once for every loop.
"""

from __future__ import annotations

import math
import types
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Final

import numpy as np
from numpy.typing import ArrayLike
from scipy import linalg

__all__ = [
    "Decision",
    "DECISIONS",
    "STICTION",
    "NO_STICTION",
    "UNDETERMINED",
    "NOT_APPLICABLE",
    "MIN_SAMPLES",
    "REGULARITY_THRESHOLD",
    "DetectorResult",
    "Oscillation",
    "prepare",
    "autocorrelation",
    "zero_crossings",
    "oscillation",
]


class Decision(StrEnum):
    """A detector's call; the first two are the words of :class:`~valve_emulator.diagnosis.answers.Answer`."""

    STICTION = "stiction"
    NO_STICTION = "no stiction"
    UNDETERMINED = "undetermined"       # the method ran but cannot decide (too short, flat, no oscillation)
    NOT_APPLICABLE = "not applicable"   # the method does not apply to this loop (e.g. an integrating plant)


STICTION: Final = Decision.STICTION
NO_STICTION: Final = Decision.NO_STICTION
UNDETERMINED: Final = Decision.UNDETERMINED
NOT_APPLICABLE: Final = Decision.NOT_APPLICABLE
DECISIONS: Final = tuple(Decision)
#: Fewer samples than this and no detector decides (it answers "undetermined", saying why).
MIN_SAMPLES: Final = 64
#: Thornhill et al. (2003): an oscillation is regular when r > 1.
REGULARITY_THRESHOLD: Final = 1.0
_MAX_LAG_FRACTION: Final = 0.75
_MIN_PERIOD_ESTIMATES: Final = 2


@dataclass(frozen=True)
class DetectorResult:
    """The verdict of one detector on one loop.

    Attributes
    ----------
    method : the detector's registry name (``"horch"``, ``"he"``, ``"bicoherence"``).
    decision : a :class:`Decision` (given as the enum or its word).
    indices : the method's numbers (its index, the oscillation period in s, ...), read-only.
    reason : one line saying why, with the deciding numbers and thresholds.
    """

    method: str
    decision: Decision
    indices: Mapping[str, float] = field(default_factory=dict)
    reason: str = ""

    def __post_init__(self) -> None:
        if self.decision not in DECISIONS:
            raise ValueError(f"decision must be one of {tuple(str(d) for d in DECISIONS)}, got {self.decision!r}")
        object.__setattr__(self, "decision", Decision(self.decision))
        object.__setattr__(self, "indices", types.MappingProxyType({k: float(v) for k, v in
                                                                    dict(self.indices).items()}))

    @property
    def stiction(self) -> bool:
        """True when the detector calls stiction."""
        return self.decision == STICTION

    def report(self) -> str:
        nums = ", ".join(f"{k}={v:.4g}" for k, v in self.indices.items())
        return f"{self.method}: {self.decision} ({self.reason})" + (f" [{nums}]" if nums else "")


@dataclass(frozen=True)
class Oscillation:
    """Result of the regularity test: ``period`` in samples (NaN without one) and ``regularity`` r."""

    period: float
    regularity: float
    n_estimates: int

    @property
    def regular(self) -> bool:
        return self.n_estimates >= _MIN_PERIOD_ESTIMATES and self.regularity > REGULARITY_THRESHOLD


def prepare(op: ArrayLike, pv: ArrayLike, sp: ArrayLike | None, dt: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Check and convert the inputs shared by every detector.

    ``op`` and ``pv`` must be one-dimensional, of equal length and finite; ``dt`` finite and > 0. ``sp`` is
    used only when it is finite everywhere (a recording without set point stores all-NaN); otherwise ``None``.
    """
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)) or not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a sample time in seconds > 0, got {dt!r}")
    arrays = []
    for name, x in (("op", op), ("pv", pv)):
        a = np.asarray(x, dtype=float)
        if a.ndim != 1:
            raise ValueError(f"{name} must be one-dimensional, got shape {a.shape}")
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise ValueError(f"{name} must be finite, got {float(a[bad[0]])!r} at index {int(bad[0])}")
        arrays.append(a)
    if arrays[0].shape != arrays[1].shape:
        raise ValueError(f"op and pv must have the same length, got {arrays[0].size} and {arrays[1].size}")
    s = None
    if sp is not None:
        s = np.asarray(sp, dtype=float)
        if s.shape != arrays[0].shape:
            raise ValueError(f"sp must have the same length as op and pv, got {s.size} and {arrays[0].size}")
        if not np.all(np.isfinite(s)):
            s = None
    return arrays[0], arrays[1], s


def autocorrelation(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Biased autocorrelation coefficients ``ρ(0..max_lag)`` of ``x`` (mean removed), via FFT."""
    x = x - x.mean()
    n = x.size
    spec = np.fft.rfft(x, 2 * n)
    acov = np.fft.irfft(spec * np.conj(spec), 2 * n)[: max_lag + 1]
    return acov / acov[0] if acov[0] > 0 else np.zeros(max_lag + 1)


def zero_crossings(y: np.ndarray) -> np.ndarray:
    """Positions (fractional indices, linear interpolation) where ``y`` changes sign."""
    s = np.sign(y)
    idx = np.flatnonzero(s[:-1] * s[1:] < 0)
    exact = np.flatnonzero(s == 0)
    pos = idx + y[idx] / (y[idx] - y[idx + 1])
    return np.sort(np.concatenate((pos, exact.astype(float))))


def detrend(x: np.ndarray) -> np.ndarray:
    """``x`` (1-D) less its least-squares straight line: ``scipy.signal.detrend(x)``'s own computation (the same
    design matrix and ``scipy.linalg.lstsq`` call, the same bits), without importing :mod:`scipy.signal`, whose
    import (with the :mod:`scipy.stats` it pulls in) cost a first diagnosis ~0.6 s for this one function."""
    n = x.size
    design = np.ones((n, 2))
    design[:, 0] = np.arange(1, n + 1, dtype=float) / n
    column = x.reshape(n, 1)
    coef = linalg.lstsq(design, column)[0]
    return (column - design @ coef).reshape(n)


def oscillation(x: ArrayLike) -> Oscillation:
    """Thornhill et al.'s regularity test on ``x`` (see the module docstring)."""
    x = np.asarray(x, dtype=float)
    if x.size < 8:
        return Oscillation(math.nan, 0.0, 0)
    x = detrend(x)
    if not np.any(x):
        return Oscillation(math.nan, 0.0, 0)
    rho = autocorrelation(x, int(_MAX_LAG_FRACTION * (x.size - 1)))
    z = zero_crossings(rho)
    periods = z[2:] - z[:-2]
    if periods.size < _MIN_PERIOD_ESTIMATES:
        return Oscillation(float(periods.mean()) if periods.size else math.nan, 0.0, int(periods.size))
    sd = float(np.std(periods, ddof=1))
    r = math.inf if sd == 0 else float(periods.mean()) / (3.0 * sd)
    return Oscillation(float(periods.mean()), r, int(periods.size))
