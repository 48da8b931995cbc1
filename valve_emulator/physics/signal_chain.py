"""The valve's signal chain, each piece usable alone.

controller output (mA) --look-up table--> OP (% travel) --saturate 0..100--> stiction --> MV (% travel)
--inherent flow characteristic--> flow (% of maximum) ; and MV --position transmitter--> mA.

The look-up table is the 2003 paper's: "the control signal has been translated to the percentage of valve
travel with the help of a linear look-up table" (4-20 mA by default; any strictly monotone table). Outside the
table the last segment is extended linearly, so 3.8 mA reads as -1.25 % and saturation (not the table) decides
what the valve does with it.

Inherent characteristics on travel x in [0, 1] (Choudhury et al. 2005; ISA-75.11):
linear f = x; equal percentage f = R**(x - 1) with rangeability R (so f(0) = 1/R, not 0);
quick opening f = sqrt(x). Flow is returned in % (100 f).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import ArrayLike

from valve_emulator.physics.stiction import DEFAULT_MODEL, StictionBank

__all__ = [
    "CHARACTERISTICS",
    "DEFAULT_MA_TABLE",
    "LookupTable",
    "Characteristic",
    "saturate",
    "ValveChain",
]

CHARACTERISTICS: Final = ("linear", "equal_percentage", "quick_opening")
DEFAULT_MA_TABLE: Final = ((4.0, 0.0), (20.0, 100.0))


@dataclass(frozen=True)
class LookupTable:
    """Piecewise-linear map between mA and % travel, linear extension beyond the ends.

    ``points`` is a sequence of ``(mA, %)`` pairs with mA strictly increasing and % strictly monotone, so the
    map is invertible (``to_ma``) for the position transmitter.
    """

    points: tuple[tuple[float, float], ...] = DEFAULT_MA_TABLE

    def __post_init__(self) -> None:
        pts = np.asarray(self.points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2:
            raise ValueError(f"ma_table must be a list of at least two [mA, %] pairs, got {self.points!r}")
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"ma_table must be finite, got {self.points!r}")
        if not np.all(np.diff(pts[:, 0]) > 0):
            raise ValueError(f"ma_table mA values must be strictly increasing, got {pts[:, 0].tolist()}")
        dp = np.diff(pts[:, 1])
        if not (np.all(dp > 0) or np.all(dp < 0)):
            raise ValueError(f"ma_table % values must be strictly monotone, got {pts[:, 1].tolist()}")
        object.__setattr__(self, "points", tuple((float(a), float(b)) for a, b in pts))

    @staticmethod
    def _interp(x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
        if xp[0] > xp[-1]:
            xp, fp = xp[::-1], fp[::-1]
        y = np.interp(x, xp, fp)
        lo, hi = x < xp[0], x > xp[-1]
        y = np.where(lo, fp[0] + (x - xp[0]) * (fp[1] - fp[0]) / (xp[1] - xp[0]), y)
        return np.where(hi, fp[-1] + (x - xp[-1]) * (fp[-1] - fp[-2]) / (xp[-1] - xp[-2]), y)

    def to_pct(self, ma: ArrayLike) -> np.ndarray:
        pts = np.asarray(self.points)
        return self._interp(np.asarray(ma, dtype=float), pts[:, 0], pts[:, 1])

    def to_ma(self, pct: ArrayLike) -> np.ndarray:
        pts = np.asarray(self.points)
        return self._interp(np.asarray(pct, dtype=float), pts[:, 1], pts[:, 0])


def saturate(pct: ArrayLike, lo: float = 0.0, hi: float = 100.0) -> np.ndarray:
    """Clip valve travel to its stops."""
    return np.clip(np.asarray(pct, dtype=float), lo, hi)


#: Rangeability of an equal-percentage valve when none is given: the flow at the lowest controllable travel is
#: 1/R of full flow. Valve handbooks give 20–50 for equal-percentage globe valves; 50 is the figure textbooks
#: draw the characteristic with, and the default everywhere in this package (config, diagnosis, twin).
DEFAULT_RANGEABILITY = 50.0


@dataclass(frozen=True)
class Characteristic:
    """Inherent flow characteristic: flow % as a function of travel %."""

    kind: str = "linear"
    rangeability: float = DEFAULT_RANGEABILITY

    def __post_init__(self) -> None:
        if self.kind not in CHARACTERISTICS:
            raise ValueError(f"characteristic must be one of {', '.join(CHARACTERISTICS)}; got {self.kind!r}")
        if not (np.isfinite(self.rangeability) and self.rangeability > 1.0):
            raise ValueError(f"rangeability must be > 1, got {self.rangeability!r}")

    def flow(self, travel: ArrayLike) -> np.ndarray:
        x = np.clip(np.asarray(travel, dtype=float), 0.0, 100.0) / 100.0
        if self.kind == "linear":
            f = x
        elif self.kind == "equal_percentage":
            f = self.rangeability ** (x - 1.0)
        else:
            f = np.sqrt(x)
        return 100.0 * f

    def travel(self, flow: ArrayLike) -> np.ndarray:
        """Inverse of :meth:`flow` (flow % -> travel %), clipped to the characteristic's range."""
        f = np.asarray(flow, dtype=float) / 100.0
        if self.kind == "linear":
            x = np.clip(f, 0.0, 1.0)
        elif self.kind == "equal_percentage":
            x = 1.0 + np.log(np.clip(f, 1.0 / self.rangeability, 1.0)) / np.log(self.rangeability)
        else:
            x = np.clip(f, 0.0, 1.0) ** 2
        return 100.0 * x

    def gain(self, travel: ArrayLike) -> np.ndarray:
        """Local slope d(flow)/d(travel) (dimensionless), e.g. for describing-function analysis."""
        x = np.clip(np.asarray(travel, dtype=float), 0.0, 100.0) / 100.0
        if self.kind == "linear":
            return np.ones_like(x)
        if self.kind == "equal_percentage":
            return np.log(self.rangeability) * self.rangeability ** (x - 1.0)
        return 0.5 / np.sqrt(np.maximum(x, 1e-12))


class ValveChain:
    """``n`` complete valves: mA or % in, MV and flow out, position transmitter mA back.

    Parameters
    ----------
    n : number of valves.
    S, J, model, rest_samples : stiction, see :class:`~valve_emulator.physics.stiction.StictionBank`.
    characteristic : :class:`Characteristic` shared by all valves, or one per valve.
    table : :class:`LookupTable` for mA <-> % (the same table serves the position transmitter).
    """

    def __init__(self, n: int, *, S: ArrayLike = 0.0, J: ArrayLike = 0.0, model: str = DEFAULT_MODEL,
                 rest_samples: ArrayLike = 1,
                 characteristic: Characteristic | Sequence[Characteristic] = Characteristic(),
                 table: LookupTable = LookupTable()) -> None:
        self.stiction = StictionBank(n, S=S, J=J, model=model, rest_samples=rest_samples)
        self.table = table
        chars = [characteristic] * n if isinstance(characteristic, Characteristic) else list(characteristic)
        if len(chars) != n:
            raise ValueError(f"characteristic must be one or {n} Characteristic objects, got {len(chars)}")
        self._groups = _group_characteristics(chars)
        self.n = n

    def reset(self, op0: ArrayLike, direction: ArrayLike = 1) -> None:
        self.stiction.reset(saturate(op0), direction)

    def step_pct(self, op_pct: ArrayLike) -> np.ndarray:
        """One sample with OP in % travel; returns MV (% travel)."""
        return self.stiction.step(saturate(op_pct))

    def step_ma(self, op_ma: ArrayLike) -> np.ndarray:
        """One sample with the controller output in mA; returns MV (% travel)."""
        return self.step_pct(self.table.to_pct(op_ma))

    def flow(self, mv: ArrayLike) -> np.ndarray:
        mv = np.broadcast_to(np.asarray(mv, dtype=float), (self.n,))
        out = np.empty(self.n)
        for char, idx in self._groups:
            out[idx] = char.flow(mv[idx])
        return out

    def position_ma(self, mv: ArrayLike) -> np.ndarray:
        """Position transmitter: MV (% travel) -> mA through the same table."""
        return self.table.to_ma(mv)


def _group_characteristics(chars: list[Characteristic]) -> list[tuple[Characteristic, np.ndarray]]:
    groups: dict[Characteristic, list[int]] = {}
    for i, c in enumerate(chars):
        groups.setdefault(c, []).append(i)
    return [(c, np.asarray(idx)) for c, idx in groups.items()]
