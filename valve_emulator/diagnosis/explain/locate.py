r"""Locate a mismatch in time and in operating conditions.

Windows
-------
The squared residual is smoothed by a moving average over ``w`` samples (about the plant's response time,
so one slip or one set-point response is one bump). Seeds are the samples above the level at which the
highest-energy samples first hold :data:`SHARE` of the total (the shortest time that explains that share);
a window is a run above half that level that contains a seed (hysteresis, so an evenly high stretch is one
window), with gaps shorter than ``w`` closed, runs shorter than ``w/2`` dropped and at most
:data:`MAX_WINDOWS` kept (the most energetic). A residual that is uniform in time
gives windows covering about :data:`SHARE` of the record, which the time share reported alongside shows.

What the windows line up with
-----------------------------
Each operating condition in which a missing piece of physics shows is a mask over the samples:

* *after OP reversals*: within the response horizon after a turning point of OP (a turn counts when OP
  moves back by more than the hysteresis ``h`` from its running extreme; ``h`` is 3 noise standard
  deviations of OP, robustly from the median absolute OP difference, and at least 5 % of the OP span);
* *fast OP changes*: the top decile of |ΔOP| smoothed over ``w``;
* *high OP* / *low OP*: top / bottom third of the OP level;
* *OP saturated*: OP at or beyond 0.5 % of its stops.

For each mask the *lift* is (share of residual energy in the mask) / (share of time in the mask); a lift
well above 1 says where the mismatch lives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SHARE", "MAX_WINDOWS", "Alignment", "Located", "locate", "condition_masks", "energy_windows",
           "turning_points"]

#: Share of the residual energy the windows must hold.
SHARE = 0.5
#: Most windows reported.
MAX_WINDOWS = 12


@dataclass(frozen=True)
class Alignment:
    """How the residual energy falls in one operating condition."""

    condition: str
    energy_share: float
    time_share: float

    @property
    def lift(self) -> float:
        return self.energy_share / self.time_share if self.time_share > 0 else float("nan")

    def sentence(self) -> str:
        return (f"{100 * self.energy_share:.0f} % of it lies {self.condition} "
                f"({100 * self.time_share:.0f} % of the time)")


@dataclass(frozen=True)
class Located:
    """Windows (s) where a residual concentrates, and its alignment with operating conditions."""

    windows: tuple[tuple[float, float], ...]
    energy_share: float
    time_share: float
    alignments: tuple[Alignment, ...]   # sorted by lift, highest first

    @property
    def strongest(self) -> Alignment | None:
        return self.alignments[0] if self.alignments else None


def _smooth(x: np.ndarray, w: int) -> np.ndarray:
    if w <= 1:
        return x.astype(float)
    c = np.concatenate([[0.0], np.cumsum(x, dtype=float)])
    half = w // 2
    idx = np.arange(x.size)
    lo, hi = np.clip(idx - half, 0, x.size), np.clip(idx - half + w, 0, x.size)
    return (c[hi] - c[lo]) / np.maximum(hi - lo, 1)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index runs where ``mask`` is True."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def energy_windows(t: np.ndarray, energy: np.ndarray, w: int) -> tuple[list[tuple[float, float]], np.ndarray]:
    """Windows holding :data:`SHARE` of a non-negative energy signal; also their sample mask."""
    e = _smooth(np.maximum(energy, 0.0), w)
    total = e.sum()
    if total <= 0:
        return [], np.zeros(t.size, dtype=bool)
    order = np.sort(e)[::-1]
    level = order[int(np.searchsorted(np.cumsum(order), SHARE * total))]
    seed = e >= level
    # Hysteresis: a window grows from its seeds while the energy stays above half the level, so a long,
    # evenly high stretch is one window rather than fragments picked out by noise.
    mask = np.zeros_like(seed)
    for a, b in _runs(e >= 0.5 * level):
        if seed[a:b].any():
            mask[a:b] = True
    for a, b in _runs(~mask):  # close short gaps
        if a > 0 and b < mask.size and b - a < w:
            mask[a:b] = True
    runs = [(a, b) for a, b in _runs(mask) if b - a >= max(1, w // 2)]
    runs = sorted(runs, key=lambda r: -e[r[0]:r[1]].sum())[:MAX_WINDOWS]
    keep = np.zeros(t.size, dtype=bool)
    for a, b in runs:
        keep[a:b] = True
    return [(float(t[a]), float(t[b - 1])) for a, b in sorted(runs)], keep


def turning_points(x: np.ndarray, h: float) -> np.ndarray:
    """Indices of ``x``'s turning points with hysteresis ``h``: an extreme counts as a turn once ``x`` has come
    back from it by more than ``h``, so that noise smaller than ``h`` makes none. Before the first turn ``x`` has
    no direction until it has moved by more than ``h``; the extreme still running at the end is not a turn."""
    x = np.asarray(x, dtype=float)
    turns: list[int] = []
    if x.size == 0:
        return np.array(turns, dtype=int)
    lo = hi = ext = x[0]
    k_lo = k_hi = k_ext = 0
    direction = 0  # unknown until x has moved by more than h
    for k in range(1, x.size):  # a small state machine over a 1-D array: clearer than vectorised tricks
        v = x[k]
        if direction == 0:
            if v > hi:
                hi, k_hi = v, k
            if v < lo:
                lo, k_lo = v, k
            if hi - lo > h:
                direction = 1 if k_hi > k_lo else -1
                ext, k_ext = (hi, k_hi) if direction == 1 else (lo, k_lo)
        elif direction * (v - ext) > 0:
            ext, k_ext = v, k
        elif direction * (ext - v) > h:
            turns.append(k_ext)
            direction = -direction
            ext, k_ext = v, k
    return np.array(turns, dtype=int)


def _reversal_mask(op: np.ndarray, horizon: int, span: float) -> np.ndarray:
    dop = np.diff(op)
    noise = 1.4826 * np.median(np.abs(dop - np.median(dop))) / np.sqrt(2.0)
    h = max(3.0 * noise, 0.05 * span, 1e-9)
    mask = np.zeros(op.size, dtype=bool)
    for k in turning_points(op, h):
        mask[k:k + horizon] = True
    return mask


def condition_masks(op: np.ndarray, *, w: int, horizon: int) -> dict[str, np.ndarray]:
    """The operating-condition masks of the module docstring, keyed by a phrase for sentences."""
    span = float(np.ptp(op))
    fast = _smooth(np.abs(np.diff(op, prepend=op[0])), w)
    lo, hi = np.percentile(op, [100 / 3, 200 / 3])
    return {
        "after OP reversals": _reversal_mask(op, horizon, span),
        "during fast OP changes": fast >= np.percentile(fast, 90),
        "at high OP": op >= hi,
        "at low OP": op <= lo,
        "with OP saturated": (op <= 0.5) | (op >= 99.5),
    }


def locate(t: np.ndarray, op: np.ndarray, energy: np.ndarray, *, dt: float, response_time: float,
           masks: dict[str, np.ndarray] | None = None) -> Located:
    """Windows and alignments of a residual energy signal (squared residual, or an improvement of it).

    Parameters
    ----------
    t, op : time (s) and OP (% travel).
    energy : per-sample energy (e.g. ``r**2``), negative values count as 0.
    dt : sample step (s).
    response_time : plant response horizon (s), e.g. dead time + 2 × time constant.
    masks : precomputed :func:`condition_masks` (computed here when None).
    """
    w = max(3, int(round(response_time / dt / 2)))
    horizon = max(2, int(round(response_time / dt)))
    windows, inside = energy_windows(t, energy, w)
    e = np.maximum(energy, 0.0)
    total = e.sum()
    masks = condition_masks(op, w=w, horizon=horizon) if masks is None else masks
    aligns = []
    for name, m in masks.items():
        if m.any() and total > 0:
            label = name.replace("after OP reversals", f"within {horizon * dt:.3g} s after OP reversals")
            aligns.append(Alignment(label, float(e[m].sum() / total), float(m.mean())))
    aligns.sort(key=lambda a: -a.lift)
    share = float(e[inside].sum() / total) if total > 0 else 0.0
    return Located(tuple(windows), share, float(inside.mean()), tuple(aligns))
