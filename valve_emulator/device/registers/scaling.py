"""Per-loop register scalings: PV range, mA table, OP limits and word order of each emulated unit.

Pure (numpy and the physics signal chain). :class:`Scaling` holds, for ``n`` units at once, the constants
that the register codec (:mod:`valve_emulator.device.registers`) needs to turn model values into register
words and back; the scales themselves come from the register table.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from valve_emulator.device.registers.table import register
from valve_emulator.device.registers.words import ABCD, WordOrder, as_word_order
from valve_emulator.physics.signal_chain import DEFAULT_MA_TABLE, LookupTable

__all__ = ["Scaling"]

_OP_SCALE: Final = register("op_pct").scale    # raw per % travel
_MA_SCALE: Final = register("op_ma").scale     # raw per mA


def _raw_range(lo: np.ndarray, hi: np.ndarray, scale: int) -> np.ndarray:
    """(n, 2) raw range whose every value decodes inside ``lo..hi`` (the float fuzz keeps exact ends)."""
    return np.column_stack([np.ceil(lo * scale - 1e-9), np.floor(hi * scale + 1e-9)])


@dataclass(frozen=True, eq=False)
class Scaling:
    """Per-unit constants that turn model values into register words, for ``n`` units (one per loop).

    Parameters
    ----------
    pv_lo, pv_hi : arrays (n,), the engineering range mapped onto 0..10000 of ``pv`` and ``sp``.
    has_controller : bool array (n,), loops with an internal controller.
    tables : one :class:`~valve_emulator.physics.signal_chain.LookupTable` (mA <-> %) per unit.
    word_order : :class:`~valve_emulator.device.registers.words.WordOrder` (or its name) of every 32-bit
        value.
    pv_units : engineering-unit strings per unit (documentation only).
    op_limits : array (n, 2) of the OP a client may write (% travel), default 0..100; a loop with a
        controller takes its ``op_limits`` (the controller refuses a manual OP outside them).

    Derived: ``op_raw_range`` and ``ma_raw_range`` (n, 2), the writable raw ranges of ``op_pct`` and
    ``op_ma`` per unit.
    """

    pv_lo: np.ndarray
    pv_hi: np.ndarray
    has_controller: np.ndarray
    tables: tuple[LookupTable, ...]
    word_order: WordOrder = ABCD
    pv_units: tuple[str, ...] = ()
    op_limits: np.ndarray | None = None

    def __post_init__(self) -> None:
        lo = np.asarray(self.pv_lo, dtype=float).reshape(-1)
        hi = np.asarray(self.pv_hi, dtype=float).reshape(-1)
        ctl = np.asarray(self.has_controller, dtype=bool).reshape(-1)
        n = lo.size
        lim = np.tile([0.0, 100.0], (n, 1)) if self.op_limits is None else np.asarray(self.op_limits, float)
        if hi.size != n or ctl.size != n or len(self.tables) != n or lim.shape != (n, 2):
            raise ValueError(f"Scaling: pv_lo, pv_hi, has_controller, tables and op_limits must all describe "
                             f"{n} units")
        if not np.all(hi > lo):
            raise ValueError(f"Scaling: pv_range must have lo < hi, got {list(zip(lo, hi))}")
        lim = np.clip(lim, 0.0, 100.0)
        if not np.all(lim[:, 1] > lim[:, 0]):
            raise ValueError(f"Scaling: op_limits must have lo < hi within 0..100, got {lim.tolist()}")
        object.__setattr__(self, "word_order", as_word_order(self.word_order))
        for name, value in (("pv_lo", lo), ("pv_hi", hi), ("has_controller", ctl), ("op_limits", lim)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "pv_units", tuple(self.pv_units) or ("",) * n)
        default = LookupTable(DEFAULT_MA_TABLE)
        # Units that share a table (the usual case: every unit the default one) are converted together.
        groups: dict[tuple, list[int]] = {}
        for i, t in enumerate(self.tables):
            groups.setdefault(t.points, []).append(i)
        # The default table is linear: convert those units in one vectorised expression each tick.
        object.__setattr__(self, "_custom", tuple(sorted(i for points, idx in groups.items()
                                                         if points != default.points for i in idx)))
        op_raw = _raw_range(lim[:, 0], lim[:, 1], _OP_SCALE)
        object.__setattr__(self, "op_raw_range", op_raw.astype(np.int64))
        ma = np.empty((n, 2))
        for idx in groups.values():
            ma[idx] = self.tables[idx[0]].to_ma(lim[idx])
        ma = np.sort(ma, axis=1)
        ma_raw = _raw_range(ma[:, 0], ma[:, 1], _MA_SCALE)
        object.__setattr__(self, "ma_raw_range", np.clip(ma_raw, 0, 65535).astype(np.int64))

    @property
    def n(self) -> int:
        return self.pv_lo.size

    @classmethod
    def build(cls, n: int, *, pv_range: Sequence[float] | Sequence[Sequence[float]] = (0.0, 100.0),
              has_controller: Any = False, ma_table: Any = None, word_order: WordOrder | str = ABCD,
              pv_units: str | Sequence[str] = "", op_limits: Sequence[float] = (0.0, 100.0)) -> Scaling:
        """Convenience constructor broadcasting one setting to ``n`` units (``ma_table=None``: 4–20 mA)."""
        rng = np.broadcast_to(np.asarray(pv_range, dtype=float), (n, 2))
        table = LookupTable(tuple(map(tuple, ma_table))) if ma_table is not None else LookupTable()
        units = (pv_units,) * n if isinstance(pv_units, str) else tuple(pv_units)
        return cls(rng[:, 0].copy(), rng[:, 1].copy(), np.broadcast_to(has_controller, (n,)).copy(),
                   (table,) * n, word_order, units, np.broadcast_to(np.asarray(op_limits, float), (n, 2)))

    @classmethod
    def from_config(cls, config: Any) -> Scaling:
        """Scalings of a ``ServerConfig`` (one unit per loop, in ``config.loops`` order)."""
        loops = config.loops
        rng = np.array([lp.plant.pv_range for lp in loops], dtype=float).reshape(len(loops), 2)
        made: dict[tuple, LookupTable] = {}   # loops with the same table share one (checked once)
        tables = tuple(made[t] if t in made else made.setdefault(t, LookupTable(tuple(map(tuple, t))))
                       for t in (lp.valve.ma_table for lp in loops))
        limits = [lp.controller.op_limits if lp.controller is not None else (0.0, 100.0) for lp in loops]
        return cls(rng[:, 0].copy(), rng[:, 1].copy(), np.array([lp.controller is not None for lp in loops]),
                   tables, config.device.word_order, tuple(lp.plant.units for lp in loops),
                   np.array(limits, dtype=float).reshape(len(loops), 2))

    # --- the loop current, shared by the compiled encoder and the codec -------------------------------

    @property
    def linear_ma(self) -> bool:
        """Is every unit's loop current the default ``4 + 0.16·OP`` mA (no custom mA table)?"""
        return not self._custom

    def op_to_ma_at(self, op: float, index: int) -> float:
        """:meth:`op_to_ma` of one OP of unit ``index`` (a write's echo in the image), the same number."""
        if index not in self._custom:
            return 4.0 + 0.16 * float(op)
        return float(self.op_to_ma(op, np.array([index]))[0])

    def op_to_ma(self, op: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
        """OP (% travel) of units ``index`` (default all) -> loop current in mA."""
        op = np.atleast_1d(np.asarray(op, dtype=float))
        ma = 4.0 + 0.16 * op
        if not self._custom:   # every table the default linear one (the usual case, at every tick)
            return ma
        idx = np.arange(self.n) if index is None else np.atleast_1d(index)
        for i in self._custom:
            sel = idx == i
            if np.any(sel):
                ma = np.where(sel, self.tables[i].to_ma(op), ma)
        return ma
