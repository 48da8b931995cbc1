r"""Put a jittered recording on a uniform time grid, or refuse it when it has real gaps.

The diagnosis needs uniform sampling (its plant models are discrete in Δt). The recorder
(``valve_emulator/clients/recorder.py``) polls a device over Modbus: with ``--period`` a row can come a tick late, so a
1 s series holds steps of 1.2 s and 0.8 s. Such a record is resampled onto the grid
``t_0 + kΔt`` (Δt the median step), each signal the way it behaves between samples:

* **OP** and **SP** are held (zero-order hold): a controller output is a value written and held until the
  next write, so at a grid time the valve saw the last value written before it;
* **PV** and **MV** are interpolated linearly: they are measurements of continuous quantities.

A step longer than :data:`MAX_GAP` sample times is a real gap (rows lost, a recorder stopped): no
interpolation can restore what happened in it, so it is refused with its line number (the header is line 1).
Steps within :data:`TOLERANCE` of Δt are left alone.
"""

from __future__ import annotations

import numpy as np

from valve_emulator.recordings.errors import RecordingError
from valve_emulator.recordings.recording import Recording

__all__ = ["regularize", "MAX_GAP", "TOLERANCE"]

#: Longest step (in median sample times) bridged by resampling.
MAX_GAP = 3.0
#: Relative deviation from the median step below which a record counts as uniform (as in ``prepare``).
TOLERANCE = 0.01


def _hold(t: np.ndarray, x: np.ndarray, grid: np.ndarray) -> np.ndarray:
    i = np.searchsorted(t, grid + 1e-9 * (t[-1] - t[0] + 1.0), side="right") - 1
    return x[np.clip(i, 0, t.size - 1)]


def _linear(t: np.ndarray, x: np.ndarray, grid: np.ndarray) -> np.ndarray:
    if np.all(np.isnan(x)):
        return np.full(grid.size, np.nan)
    return np.interp(grid, t, x)


def regularize(rec: Recording, *, max_gap: float = MAX_GAP) -> tuple[Recording, str | None]:
    """``(recording on a uniform grid, note)``; the note is None when nothing had to be done.

    Raises
    ------
    RecordingError
        A step longer than ``max_gap`` median steps (naming the line and the step).
    """
    n = len(rec)
    if n < 3:
        return rec, None
    t = np.asarray(rec.t, dtype=float)
    steps = np.diff(t)
    dt = float(np.median(steps))
    src = rec.source or "recording"
    gaps = np.flatnonzero(steps > max_gap * dt)
    if gaps.size:
        i = int(gaps[0])
        raise RecordingError(f"{src}: line {i + 3}: a gap of {steps[i]:g} s after t = {t[i]:g} s, more than "
                             f"{max_gap:g} sample times of {dt:g} s; split the record there (resampling only "
                             "bridges polling jitter)", source=src, line=i + 3)
    off = np.abs(steps - dt) > TOLERANCE * dt
    if not off.any():
        return rec, None
    grid = t[0] + dt * np.arange(int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1)
    extra = {k: _hold(t, np.asarray(v, dtype=float), grid) for k, v in rec.extra.items()}
    out = Recording(grid, _hold(t, np.asarray(rec.sp, dtype=float), grid), _hold(t, np.asarray(rec.op), grid),
                    _linear(t, np.asarray(rec.mv, dtype=float), grid), _linear(t, np.asarray(rec.pv), grid),
                    extra=extra, source=rec.source)
    worst = float(np.max(np.abs(steps - dt)))
    note = (f"resampled onto a uniform {dt:g} s grid: {int(off.sum())} of {steps.size} steps were irregular "
            f"(up to {worst:.3g} s off); OP and SP held, PV interpolated linearly ({n} rows → {grid.size})")
    return out, note
