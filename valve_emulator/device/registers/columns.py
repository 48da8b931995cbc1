"""Every loop's served row of a configured map at once: one numpy pass per register, at each tick.

Pure (numpy). :func:`~.codec.encode_loop` states the rules one register and one loop at a time; a device whose
``device.register_map`` is configured encodes its rows with :func:`encode_rows`, the same rules over all
loops as numpy columns (a test keeps the two equal word for word), so its tick costs a few numpy operations
per tag whatever the number of loops. The standard map has its compiled kernel (:mod:`~.kernel`).
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Any, Final

import numpy as np

from valve_emulator.device.registers.mapping import RegisterMap
from valve_emulator.device.registers.scaling import Scaling
from valve_emulator.device.registers.table import (
    CONTROLLER_QUANTITIES,
    MAP_VERSION,
    Conversion,
    Fault,
    Register,
    Status,
)
from valve_emulator.device.registers.words import CDAB, DataType

__all__ = ["encode_rows"]

_MEASURED: Final = ("op", "mv", "flow", "pv", "sp", "kc", "ti", "td", "S", "J")


def _column(state: Any, name: str, n: int, dtype: type, optional: bool = False) -> np.ndarray:
    value = getattr(state, name, None) if optional else getattr(state, name)
    if value is None:
        return np.zeros(n, dtype=dtype)
    return np.broadcast_to(np.asarray(value, dtype=dtype), (n,))


def loop_columns(state: Any, n: int, *, tick: int, overruns: int, time: float,
                 alarms: np.ndarray | None = None, quantities: Collection[str] | None = None) -> dict[str, np.ndarray]:
    """:func:`~.codec.loop_values` of every loop: quantity -> array (n,). ``alarms``: every loop's alarm word
    (:class:`~valve_emulator.device.alarms.PvAlarms`; the bank does not hold them), else ``state.alarms`` or 0.
    ``quantities``: only these (and ``controller``), for a map that shows a few (default every one)."""
    def want(quantity: str) -> bool:
        return quantities is None or quantity in quantities

    values = {name: _column(state, name, n, float) for name in _MEASURED if want(name)}
    controller = _column(state, "has_controller", n, bool)
    values["controller"] = controller
    auto = _column(state, "auto", n, bool) & controller if want("auto") or want("status") else None
    seized = _column(state, "frozen", n, bool, optional=True) if want("fault") or want("status") else None
    if want("status"):   # codec.status_word, over the loops
        status = np.where(_column(state, "stuck", n, bool), int(Status.STUCK), int(Status.MOVING))
        for on, bit in ((_column(state, "sat_low", n, bool), Status.SAT_LOW),
                        (_column(state, "sat_high", n, bool), Status.SAT_HIGH), (controller, Status.CONTROLLER),
                        (auto, Status.AUTO), (seized, Status.SEIZED)):
            status = status | np.where(on, int(bit), 0)
        values["status"] = status
    derived = {
        "auto": lambda: auto.astype(np.int64),
        "load": lambda: _column(state, "load", n, float, optional=True),
        "noise": lambda: _column(state, "noise_std", n, float, optional=True),
        "fault": lambda: np.where(seized, int(Fault.SEIZED), 0),
        "map_version": lambda: np.full(n, MAP_VERSION),
        "tick": lambda: np.full(n, int(tick)),
        "overruns": lambda: np.full(n, int(overruns)),
        "time": lambda: np.full(n, float(time)),
        "alarms": lambda: (_column(state, "alarms", n, int, optional=True) if alarms is None
                           else np.asarray(alarms, dtype=np.int64)),
    }
    values.update((quantity, column()) for quantity, column in derived.items() if want(quantity))
    return values


def _scaled(reg: Register, x: np.ndarray, scaling: Scaling) -> np.ndarray:
    """The unrounded raw values of a scaled integer register (``codec._scaled``, over the loops)."""
    lo, hi = scaling.pv_lo, scaling.pv_hi
    conversion = reg.conversion
    if conversion is Conversion.COUNTS:
        e_lo, e_hi = (lo, hi) if reg.span is None else reg.span
        c_lo, c_hi = reg.counts
        return c_lo + (x - e_lo) * (c_hi - c_lo) / (e_hi - e_lo)
    if conversion is Conversion.PV_RANGE:
        return (x - lo) * (reg.scale * 100.0 / (hi - lo))
    if conversion is Conversion.PV_SPAN:
        return ((lo + x) - lo) * (reg.scale * 100.0 / (hi - lo))
    if conversion is Conversion.LOOP_CURRENT:
        return scaling.op_to_ma(x) * reg.scale
    return x * reg.scale


def _raw(reg: Register, x: np.ndarray, scaling: Scaling) -> np.ndarray:
    """The integer raw values of ``reg`` for the loops' physical values ``x`` (int64, maybe negative)."""
    conversion = reg.conversion
    if conversion is Conversion.COUNTER:
        return x.astype(np.int64) % (reg.type.raw_range[1] + 1)
    if conversion in (Conversion.BITS, Conversion.FLAG):
        return (x != 0).astype(np.int64) if conversion is Conversion.FLAG else x.astype(np.int64)
    lo, hi = reg.read_range
    y = _scaled(reg, x.astype(float), scaling)
    raw = np.where(y >= lo, np.where(y > hi, hi, np.rint(np.where(np.isfinite(y), y, lo))), lo)
    if reg.zero_is_off:
        raw = np.where(np.isfinite(x) & (x > 0), raw, 0)
    return raw.astype(np.int64)


def _words(reg: Register, x: np.ndarray, scaling: Scaling) -> np.ndarray:
    """(n, width) register words of ``reg`` for the loops' physical values ``x`` (inside :func:`encode_rows`'
    ``errstate``: NaN compares and float32 overflows are the rule's, not an error)."""
    width = reg.width
    if reg.type is DataType.FLOAT32:
        bits = x.astype(np.float64).astype(np.float32).view(np.uint32).astype(np.int64)
    elif reg.type is DataType.FLOAT64:
        bits = x.astype(np.float64).view(np.uint64)
    else:
        bits = _raw(reg, x, scaling) & ((1 << (16 * width)) - 1)
    if width == 1:   # most tags: one word, no order
        return (bits & 0xFFFF).astype(np.int64).reshape(-1, 1)
    words = np.empty((bits.shape[0], width), dtype=np.int64)
    for k in range(width):                                          # high word first
        s = 16 * (width - 1 - k)
        words[:, k] = (bits >> np.uint64(s) if bits.dtype == np.uint64 else bits >> s) & 0xFFFF
    return words[:, ::-1] if (reg.word_order or scaling.word_order) is CDAB else words


def encode_rows(state: Any, scaling: Scaling, regmap: RegisterMap, *, tick: int, overruns: int,
                time: float, alarms: np.ndarray | None = None) -> np.ndarray:
    """Every loop's served row of ``regmap``: int64 (n, ``regmap.row_words``), equal to :func:`~.codec.encode_loop`
    of each loop. Registers of the internal controller read 0 on a loop without one."""
    n = scaling.n
    values = loop_columns(state, n, tick=tick, overruns=overruns, time=time, alarms=alarms,
                          quantities=regmap.quantities)
    rows = np.zeros((n, regmap.row_words), dtype=np.int64)
    with np.errstate(over="ignore", invalid="ignore"):   # once per tick, not per register
        for reg in regmap.registers:
            words = _words(reg, np.asarray(values[reg.quantity]), scaling)
            if reg.quantity in CONTROLLER_QUANTITIES:
                words[~values["controller"]] = 0
            at = regmap.word_offset(reg.table, reg.address)
            rows[:, at:at + reg.width] = words
    return rows
