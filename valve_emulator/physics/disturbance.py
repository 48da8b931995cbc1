r"""Seeded load disturbances and measurement noise for banks of loops, advanced once per sample.

Load disturbance :math:`d_i(t)` (added to the plant input, % flow) of loop *i*, by kind:

* ``none``:        :math:`d = 0`
* ``step``:        :math:`d = a` for :math:`t \ge t_s`, else 0
* ``sine``:        :math:`d = a \sin(2\pi t / P + \varphi)` (φ in radians)
* ``random_walk``: :math:`d_0 = 0,\ d_{k+1} = d_k + \sigma\sqrt{\Delta t}\,\xi_{k+1}`,
  :math:`\xi \sim N(0, 1)`; σ is the standard deviation per √s, so the variance grows as σ²t.

Measurement noise: :math:`v_k = \sigma_v \xi_k`.

Reproducibility
---------------
Each random loop owns a ``numpy.random.Generator(PCG64(...))`` seeded by
``SeedSequence(seed, spawn_key=(stream, index))`` — ``stream`` is 0 for load disturbances and 1 for
measurement noise, so the two never share numbers even under one seed, and ``index`` is the loop's
index (by default its position in the bank). A loop's sequence therefore depends only on
``(seed, stream, index)`` and its own parameters: loop *i* of a bank equals a bank of one built with
``index=[i]``, and the device tick and an offline run produce the same numbers. Normals are drawn per
loop in blocks of :data:`BLOCK` (fewer Python calls per sample) and consumed one per call to ``step``;
loops that cannot be random (not ``random_walk``, or zero noise) draw nothing.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from valve_emulator.physics._arrays import vector

__all__ = ["KINDS", "BLOCK", "DisturbanceBank", "NoiseBank"]

KINDS = ("none", "step", "sine", "random_walk")
#: Normals drawn per loop at a time.
BLOCK = 256
_STREAM_DISTURBANCE = 0
_STREAM_NOISE = 1


def _seed_and_index(seed: int, index: ArrayLike | None, n: int) -> np.ndarray:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    idx = np.arange(n) if index is None else np.asarray(index)
    if idx.shape != (n,) or not np.issubdtype(idx.dtype, np.integer) or np.any(idx < 0):
        raise ValueError(f"index must be {n} non-negative integers, got {index!r}")
    return idx


class _NormalStreams:
    """Per-loop standard normals, drawn in blocks; rows of loops without a generator stay zero."""

    def __init__(self, seed: int, stream: int, index: np.ndarray, active: np.ndarray):
        n = index.size
        self._gens = [
            np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=(stream, int(i)))))
            if a else None
            for i, a in zip(index, active)
        ]
        self._z = np.zeros((n, BLOCK))
        self._pos = BLOCK

    def next(self) -> np.ndarray:
        if self._pos == BLOCK:
            for i, g in enumerate(self._gens):
                if g is not None:
                    self._z[i] = g.standard_normal(BLOCK)
            self._pos = 0
        col = self._z[:, self._pos]
        self._pos += 1
        return col


class DisturbanceBank:
    """Load disturbances for ``n`` loops (``n = len(kinds)``), in % flow.

    Parameters
    ----------
    kinds : str or sequence of str
        One of :data:`KINDS` per loop; a single string applies to all ``n`` loops.
    dt : float
        Sample time (s), > 0.
    seed : int
        Non-negative seed shared by the bank (see the module docstring).
    n : int, optional
        Number of loops when ``kinds`` is a single string (default 1).
    amplitude, time, period, phase, std : float or array_like (n,)
        Step/sine amplitude (%), step time (s), sine period (s, > 0 for sine loops), sine phase (rad),
        random-walk standard deviation per √s (≥ 0). Parameters a kind does not use are ignored.
    index : array_like of int, optional
        Seeding index of each loop (default ``arange(n)``).
    """

    def __init__(self, kinds: str | Sequence[str], *, dt: float, seed: int, n: int | None = None,
                 amplitude: ArrayLike = 0.0, time: ArrayLike = 0.0, period: ArrayLike = 1.0,
                 phase: ArrayLike = 0.0, std: ArrayLike = 0.0, index: ArrayLike | None = None):
        if isinstance(kinds, str):
            kinds = [kinds] * (1 if n is None else int(n))
        kinds = list(kinds)
        if n is not None and n != len(kinds):
            raise ValueError(f"n={n} does not match len(kinds)={len(kinds)}")
        n = len(kinds)
        if n == 0:
            raise ValueError("kinds must name at least one loop")
        for i, k in enumerate(kinds):
            if k not in KINDS:
                raise ValueError(f"kinds[{i}] must be one of {KINDS}, got {k!r}")
        if not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
        kind = np.array([KINDS.index(k) for k in kinds])
        self._amp = vector("amplitude", amplitude, n, finite=True)
        self._time = vector("time", time, n, finite=True)
        self._period = vector("period", period, n, finite=True)
        self._phase = vector("phase", phase, n, finite=True)
        self._std = vector("std", std, n, finite=True)
        sine = kind == KINDS.index("sine")
        walk = kind == KINDS.index("random_walk")
        if np.any(self._period[sine] <= 0):
            raise ValueError(f"period must be > 0 for sine loops, got {self._period[sine].tolist()}")
        if np.any(self._std < 0):
            raise ValueError(f"std must be >= 0, got {self._std.tolist()}")
        idx = _seed_and_index(seed, index, n)
        self._n, self._dt = n, float(dt)
        self._step_mask = kind == KINDS.index("step")
        self._sine_mask = sine
        self._walk_mask = walk
        self._walk = np.zeros(n)
        self._normals = _NormalStreams(seed, _STREAM_DISTURBANCE, idx, walk & (self._std > 0))

    @property
    def n(self) -> int:
        """Number of loops."""
        return self._n

    def step(self, t: float) -> np.ndarray:
        """Disturbance at time ``t`` (s) for every loop, then advance the random walks one sample."""
        # Kinds no loop has are skipped (a fleet without disturbances: a tenth of a tick at 10^5 loops), but the
        # random-walk streams advance every sample all the same: the same draws whoever joins later.
        d = np.zeros(self._n)
        if self._step_mask.any():
            d[self._step_mask] = np.where(t >= self._time[self._step_mask], self._amp[self._step_mask], 0.0)
        s = self._sine_mask
        if s.any():
            d[s] = self._amp[s] * np.sin(2.0 * np.pi * t / self._period[s] + self._phase[s])
        w = self._walk_mask
        normals = self._normals.next()
        if w.any():
            d[w] = self._walk[w]
            # σ√dt·ξ is an exact sample of the Wiener increment over one dt.
            self._walk += self._std * np.sqrt(self._dt) * normals * w
        return d

    def step_many(self, times: ArrayLike) -> np.ndarray:
        """Equivalent to ``[step(t) for t in times]`` stacked: shape (len(times), n)."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        return np.array([self.step(t) for t in times]).reshape(times.size, self._n)


class NoiseBank:
    """Gaussian measurement noise for ``n = len(std)`` loops.

    Parameters
    ----------
    std : array_like (n,) or float
        Standard deviation per loop (PV units, ≥ 0). A scalar makes a bank of one.
    seed : int
        Non-negative seed shared by the bank (see the module docstring).
    index : array_like of int, optional
        Seeding index of each loop (default ``arange(n)``).
    """

    def __init__(self, std: ArrayLike, seed: int, *, index: ArrayLike | None = None):
        std_a = np.atleast_1d(np.asarray(std, dtype=float))
        if std_a.ndim != 1 or std_a.size == 0:
            raise ValueError(f"std must be a scalar or a 1-D array, got shape {np.shape(std)}")
        if not np.all(np.isfinite(std_a)) or np.any(std_a < 0):
            raise ValueError(f"std must be finite and >= 0, got {std_a.tolist()}")
        self._std = std_a.copy()
        self._n = std_a.size
        idx = _seed_and_index(seed, index, self._n)
        self._normals = _NormalStreams(seed, _STREAM_NOISE, idx, self._std > 0)

    @property
    def n(self) -> int:
        """Number of loops."""
        return self._n

    def step(self) -> np.ndarray:
        """Noise sample for every loop (a new array)."""
        return self._std * self._normals.next()

    def step_many(self, count: int) -> np.ndarray:
        """Equivalent to ``count`` calls of :meth:`step` stacked: shape (count, n)."""
        return np.array([self.step() for _ in range(int(count))]).reshape(int(count), self._n)
