"""The PV alarms of every loop: high and low limits, latched until acknowledged (ISA-18.2's states, simplified).

One place computes them for every interface: the device refreshes them after each tick and shows them in the
``alarms`` register (:class:`~valve_emulator.device.registers.AlarmBit`: ``pv_high``, ``pv_low``,
``unacked``), the instructor station shows and acknowledges them (``POST /api/alarms/UNIT/ack``), and the OPC
UA server turns their changes into ``AlarmConditionType`` events (:mod:`valve_emulator.opcua.alarms`).

A loop's limits are its ``plant.alarms`` (by default 10 % and 90 % of its PV range; a training scenario may
set others, :attr:`PvAlarms.lo` / :attr:`PvAlarms.hi` in place). Its alarm is one of four states
(:class:`AlarmState`), all following from two facts: is PV outside a limit now (*active*), and has the alarm
been acknowledged since it last became active (*unacked*)?

============  ========  =======  ========================================================
state         active    unacked  how it is reached
============  ========  =======  ========================================================
normal        no        no       start; an acknowledged alarm back inside its limits
unacked       yes       yes      PV leaves its limits
acked         yes       no       acknowledged while active
returned      no        yes      PV back inside its limits before anyone acknowledged it
============  ========  =======  ========================================================

Acknowledging a returned alarm makes it normal. The words are updated for every loop at once (one compiled
pass per tick); only loops whose alarm word changed are handed to the listeners.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import StrEnum

import numba
import numpy as np

from valve_emulator.device.registers import AlarmBit

__all__ = ["AlarmChange", "AlarmState", "PvAlarms", "state_of"]

_ALL_BITS = int(AlarmBit.PV_HIGH | AlarmBit.PV_LOW | AlarmBit.UNACKED)


class AlarmState(StrEnum):
    """A loop's PV alarm as the station and the operator see it."""

    NORMAL = "normal"
    UNACKED = "unacked"        # active, not acknowledged
    ACKED = "acked"            # active, acknowledged
    RETURNED = "returned"      # back inside the limits, not acknowledged yet


@dataclass(frozen=True)
class AlarmChange:
    """Loop ``index``'s alarm after a change: its ``alarms`` word (:class:`AlarmBit`), the PV and limits that
    made it, and whether it was an acknowledgement (rather than PV crossing a limit)."""

    index: int
    word: int
    pv: float
    lo: float
    hi: float
    acknowledged: bool = False

    @property
    def state(self) -> AlarmState:
        return state_of(self.word)

    @property
    def high(self) -> bool:
        return bool(self.word & AlarmBit.PV_HIGH)

    @property
    def low(self) -> bool:
        return bool(self.word & AlarmBit.PV_LOW)

    @property
    def active(self) -> bool:
        return bool(self.word & (AlarmBit.PV_HIGH | AlarmBit.PV_LOW))

    @property
    def unacked(self) -> bool:
        return bool(self.word & AlarmBit.UNACKED)


def state_of(word: int) -> AlarmState:
    """The :class:`AlarmState` an ``alarms`` word shows."""
    active = bool(word & (AlarmBit.PV_HIGH | AlarmBit.PV_LOW))
    unacked = bool(word & AlarmBit.UNACKED)
    if active:
        return AlarmState.UNACKED if unacked else AlarmState.ACKED
    return AlarmState.RETURNED if unacked else AlarmState.NORMAL


@numba.njit(cache=True)
def _update_words(pv, lo, hi, words, changed):  # pragma: no cover - compiled
    """One pass over every loop (a fleet's tick cannot afford a numpy temporary per step): the new ``alarms``
    word of each loop into ``words``, the indices that changed into ``changed``; returns how many did."""
    count = 0
    for i in range(pv.shape[0]):
        old = words[i]
        word = 1 if pv[i] > hi[i] else (2 if pv[i] < lo[i] else 0)     # PV_HIGH, PV_LOW (NaN: neither)
        unacked = old & 4                                              # UNACKED stays until acknowledged ...
        if word != 0 and (old & 3) == 0:
            unacked = 4                                                # ... and is set when the alarm rises
        word |= unacked
        if word != old:
            words[i] = word
            changed[count] = i
            count += 1
    return count


assert (int(AlarmBit.PV_HIGH), int(AlarmBit.PV_LOW), int(AlarmBit.UNACKED)) == (1, 2, 4)   # the kernel's bits
#: :meth:`PvAlarms.update`'s answer when no word changed (read only: one array for every such tick)
_NONE_CHANGED = np.zeros(0, dtype=np.int64)
_NONE_CHANGED.setflags(write=False)


class PvAlarms:
    """The PV alarms of ``n`` loops with limits ``lo`` < ``hi`` (PV units; arrays the caller may change in place).

    :meth:`update` takes the PV of every loop after a tick; :meth:`acknowledge` acknowledges one loop's alarm.
    Both call every listener in :attr:`listeners` with an :class:`AlarmChange` per loop whose word changed.
    """

    def __init__(self, lo: Sequence[float], hi: Sequence[float]) -> None:
        self.lo = np.array(lo, dtype=float)
        self.hi = np.array(hi, dtype=float)
        if self.lo.shape != self.hi.shape or self.lo.ndim != 1:
            raise ValueError(f"PvAlarms: lo and hi must be two sequences of one length, got {self.lo.shape} "
                             f"and {self.hi.shape}")
        n = self.lo.size
        #: the ``alarms`` word of every loop (:class:`AlarmBit`)
        self.words = np.zeros(n, dtype=np.int64)
        self._pv = np.full(n, np.nan)
        self._changed = np.zeros(n, dtype=np.int64)   # scratch: the indices one update changed
        #: called with an :class:`AlarmChange` for every loop whose word changed (keep them short: the tick
        #: waits for them)
        self.listeners: list[Callable[[AlarmChange], None]] = []

    @classmethod
    def of_loops(cls, loops: Sequence) -> PvAlarms:
        """The alarms of loop configs (``plant.alarm_limits`` each)."""
        limits = np.array([lp.plant.alarm_limits for lp in loops], dtype=float).reshape(-1, 2)
        return cls(limits[:, 0], limits[:, 1])

    @property
    def n(self) -> int:
        return int(self.words.size)

    def state(self, index: int) -> AlarmState:
        return state_of(int(self.words[index]))

    def update(self, pv: np.ndarray) -> np.ndarray:
        """Compare every loop's ``pv`` with its limits; returns the indices whose word changed."""
        self._pv = np.ascontiguousarray(pv, dtype=np.float64)
        count = _update_words(self._pv, self.lo, self.hi, self.words, self._changed)
        if not count:   # the usual tick
            return _NONE_CHANGED
        changed = self._changed[:count].copy()
        self._notify(changed, acknowledged=False)
        return changed

    def acknowledge(self, index: int) -> bool:
        """Acknowledge loop ``index``'s alarm; False (nothing changed) when there was nothing to acknowledge."""
        word = int(self.words[index])
        if not word & AlarmBit.UNACKED:
            return False
        self.words[index] = word & ~AlarmBit.UNACKED
        self._notify(np.array([index]), acknowledged=True)
        return True

    def change(self, index: int, *, acknowledged: bool = False) -> AlarmChange:
        """Loop ``index``'s alarm now, as the listeners are told it."""
        return AlarmChange(index=index, word=int(self.words[index]), pv=float(self._pv[index]),
                           lo=float(self.lo[index]), hi=float(self.hi[index]), acknowledged=acknowledged)

    def _notify(self, indices: np.ndarray, *, acknowledged: bool) -> None:
        for i in indices.tolist():
            change = self.change(i, acknowledged=acknowledged)
            for listener in self.listeners:
                listener(change)

    # --- snapshots ------------------------------------------------------------------------------------

    def checked_words(self, words: object) -> np.ndarray | None:
        """A snapshot's alarm words, checked: ``n`` whole numbers made of :class:`AlarmBit` bits (``ValueError``
        naming what is wrong); None (a snapshot from before alarms were kept) stays None."""
        if words is None:
            return None
        if not isinstance(words, list) or len(words) != self.n or not all(
                isinstance(w, int) and not isinstance(w, bool) and 0 <= w <= _ALL_BITS for w in words):
            raise ValueError(f"alarms must be {self.n} whole numbers 0..{_ALL_BITS} (bits of the alarms register)")
        return np.array(words, dtype=np.int64)

    def set_words(self, words: np.ndarray | None) -> None:
        """Put back a snapshot's :meth:`checked_words`; None clears every alarm (the next update raises those
        still outside their limits again)."""
        self.words = np.zeros(self.n, dtype=np.int64) if words is None else words.copy()
