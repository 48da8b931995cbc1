"""The register codec in plain Python: one register, one loop at a time, straight from the table's rules.

Pure (numpy only for the mA tables). The device encodes every loop each tick with
a compiled pass (:mod:`~valve_emulator.device.registers.kernel`); this module is what the rest uses:

- :func:`encode_value` -- the words a register shows for a physical value;
- :func:`patch` -- after an accepted write, the registers that show the written quantity, so a read in the
  same tick sees it;
- :func:`decode_write` -- a client's raw words -> validated physical changes;
- :func:`encode_loop` -- every register of one loop, the readable specification the compiled pass is
  tested against.

Encoding of a 16-bit register (the row's :class:`~.table.Conversion` gives ``y``)::

    raw = clip(round_half_even(y), read range)    NaN reads as the bottom of the range
    word = raw mod 2^16                            int16: two's complement

A 32-bit register holds the float32 (or the counter modulo 2³²) in two words in the device's word order.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Final

import numpy as np

from valve_emulator.device.registers.errors import (
    RegisterAccessError,
    RegisterAddressError,
    RegisterValueError,
)
from valve_emulator.device.registers.scaling import Scaling
from valve_emulator.device.registers.table import (
    CONTROLLER_QUANTITIES,
    MAP_VERSION,
    N_REGISTERS,
    REGISTERS,
    RW_CONTROLLER,
    RW_INSTRUCTOR,
    WRITABLE_QUANTITIES,
    Conversion,
    Fault,
    R,
    Register,
    Status,
    address_of,
    holding_at,
    showing,
)
from valve_emulator.device.registers.words import CDAB, DataType, float32_bits, split32

__all__ = ["decode_value", "decode_write", "encode_loop", "encode_value", "encode_write", "patch", "status_word",
           "write_range"]

_STATUS: Final = address_of("status")
# Written quantities that also flip a status bit: quantity -> (bit, is the bit set for this value?)
_STATUS_FLAG: Final[dict[str, tuple[Status, Callable[[Any], bool]]]] = {
    "auto": (Status.AUTO, bool),
    "fault": (Status.SEIZED, lambda v: bool(int(v) & Fault.SEIZED)),
}


def _per_range(reg: Register, scaling: Scaling, index: int) -> tuple[float, float]:
    """``(lo, k)``: bottom of the loop's PV range and raw units per PV unit (100·scale / (hi − lo))."""
    lo, hi = float(scaling.pv_lo[index]), float(scaling.pv_hi[index])
    return lo, reg.scale * 100.0 / (hi - lo)


def _scaled(reg: Register, value: float, scaling: Scaling, index: int) -> float:
    """The unrounded raw value ``y`` of a 16-bit scaled register (see the module docstring)."""
    conversion = reg.conversion
    if conversion is Conversion.PV_RANGE:
        lo, k = _per_range(reg, scaling, index)
        return (value - lo) * k
    if conversion is Conversion.PV_SPAN:   # a width w reads like the PV lo + w
        lo, k = _per_range(reg, scaling, index)
        return ((lo + value) - lo) * k
    if conversion is Conversion.LOOP_CURRENT:
        return float(scaling.op_to_ma(value, np.array([index]))[0]) * reg.scale
    return value * reg.scale


def _round_clip(y: float, lo: int, hi: int) -> int:
    """round(y) half to even, clipped to lo..hi; NaN reads as lo (bounds are integers: clip, then round)."""
    if not y >= lo:
        return lo
    if y > hi:
        return hi
    return round(y)


def encode_value(reg: Register, value: Any, scaling: Scaling, index: int) -> tuple[int, ...]:
    """The ``reg.width`` words register ``reg`` shows for the physical ``value`` of loop ``index``."""
    cdab = scaling.word_order is CDAB
    if reg.type is DataType.FLOAT32:
        return split32(float32_bits(float(value)), cdab)
    conversion = reg.conversion
    if conversion is Conversion.COUNTER:
        raw = int(value) % (reg.type.raw_range[1] + 1)
    elif conversion is Conversion.BITS:
        raw = int(value)
    elif conversion is Conversion.FLAG:
        raw = 1 if value else 0
    elif reg.zero_is_off and not (math.isfinite(value) and value > 0):
        raw = 0
    else:
        raw = _round_clip(_scaled(reg, float(value), scaling, index), *reg.read_range)
    if reg.width == 2:
        return split32(raw, cdab)
    return (raw & 0xFFFF,)


def encode_write(reg: Register, value: float, scaling: Scaling, index: int) -> tuple[int, ...]:
    """The words a client writes to ``reg`` to set the physical ``value`` of loop ``index`` (a protocol that
    carries engineering values, such as OPC UA, then writes them like any Modbus client).

    Unlike :func:`encode_value` nothing is clipped: a value beyond what the register can carry, or a flag or
    bit field that is not a whole number, raises :class:`RegisterValueError` naming the register, and a word
    outside the register's write range is refused by :func:`decode_write` as it would be over Modbus.
    """
    value = float(value)
    if reg.type is DataType.FLOAT32 or reg.width != 1:
        raise RegisterAccessError(f"register {reg.name} is not written directly", register=reg.name)
    if reg.conversion in (Conversion.FLAG, Conversion.BITS, Conversion.COUNTER) or (reg.zero_is_off and value == 0):
        raw = value
    else:
        raw = _scaled(reg, value, scaling, index)
    lo, hi = reg.type.raw_range
    if not (math.isfinite(raw) and raw == raw and lo <= round(raw) <= hi) or (
            reg.conversion in (Conversion.FLAG, Conversion.BITS) and raw != int(raw)):
        raise RegisterValueError(f"register {reg.name}: {value:g} cannot be written (raw {raw:g} outside "
                                 f"{lo}..{hi} or not a whole number)", register=reg.name, value=value,
                                 allowed=write_range(reg, scaling, index))
    return (round(raw) & 0xFFFF,)


def status_word(*, stuck: bool, sat_low: bool, sat_high: bool, controller: bool, auto: bool,
                seized: bool) -> int:
    """The ``status`` register (:class:`~.table.Status` bits); ``auto`` counts only with a controller."""
    bits = Status.STUCK if stuck else Status.MOVING
    for on, bit in ((sat_low, Status.SAT_LOW), (sat_high, Status.SAT_HIGH), (controller, Status.CONTROLLER),
                    (auto and controller, Status.AUTO), (seized, Status.SEIZED)):
        if on:
            bits |= bit
    return int(bits)


def _at(state: Any, name: str, index: int, *, optional: bool = False) -> Any:
    """Loop ``index``'s value of the state array ``name`` (a scalar applies to every loop); an optional
    array the state does not have reads as 0."""
    value = getattr(state, name, None) if optional else getattr(state, name)
    if value is None:
        return 0
    value = np.asarray(value)
    return value if value.ndim == 0 else value[index]


def encode_loop(state: Any, scaling: Scaling, index: int, *, tick: int, overruns: int,
                time: float) -> np.ndarray:
    """Every register of loop ``index``: int64 array (N_REGISTERS,) of words, one register at a time.

    ``state`` is read as :func:`~valve_emulator.device.registers.kernel.encode` describes. Registers of the
    internal controller (:data:`~.table.CONTROLLER_QUANTITIES`) read 0 on a loop without one.
    """
    controller = bool(_at(state, "has_controller", index))
    auto = bool(_at(state, "auto", index)) and controller
    seized = bool(_at(state, "frozen", index, optional=True))
    values = {name: float(_at(state, name, index)) for name in ("op", "mv", "flow", "pv", "sp", "kc", "ti", "td",
                                                                "S", "J")}
    values.update(
        auto=auto, load=float(_at(state, "load", index, optional=True)),
        noise=float(_at(state, "noise_std", index, optional=True)), fault=int(Fault.SEIZED) if seized else 0,
        alarms=int(_at(state, "alarms", index, optional=True)),
        map_version=MAP_VERSION, tick=int(tick), overruns=int(overruns), time=float(time),
        status=status_word(stuck=bool(_at(state, "stuck", index)), sat_low=bool(_at(state, "sat_low", index)),
                           sat_high=bool(_at(state, "sat_high", index)), controller=controller, auto=auto,
                           seized=seized))
    row = np.zeros(N_REGISTERS, dtype=np.int64)
    for reg in REGISTERS:
        if reg.quantity in CONTROLLER_QUANTITIES and not controller:
            continue
        row[reg.address:reg.address + reg.width] = encode_value(reg, values[reg.quantity], scaling, index)
    return row


def patch(row: np.ndarray, quantity: str, value: Any, scaling: Scaling, index: int) -> None:
    """Overwrite, in one unit's word ``row``, the registers that show ``quantity`` (after an accepted write)."""
    if quantity not in WRITABLE_QUANTITIES:
        raise KeyError(f"quantity {quantity!r} is not writable")
    for reg in showing(quantity):
        row[reg.address:reg.address + reg.width] = encode_value(reg, value, scaling, index)
    if quantity in _STATUS_FLAG:
        bit, is_set = _STATUS_FLAG[quantity]
        row[_STATUS] = (row[_STATUS] & ~int(bit)) | (int(bit) if is_set(value) else 0)


def write_range(reg: Register, scaling: Scaling, index: int) -> tuple[int, int]:
    """Raw range a write to ``reg`` may take on loop ``index`` (OP registers: within the loop's op_limits)."""
    if reg.quantity != "op":
        return reg.write
    ranges = scaling.ma_raw_range if reg.conversion is Conversion.LOOP_CURRENT else scaling.op_raw_range
    return tuple(ranges[index])


def decode_value(reg: Register, raw: int, scaling: Scaling, index: int) -> Any:
    """The physical value of a written raw word (``raw`` signed for ``int16``); inverse of :func:`encode_value`."""
    conversion = reg.conversion
    if conversion is Conversion.LOOP_CURRENT:
        lo, hi = scaling.op_limits[index]
        return float(np.clip(scaling.tables[index].to_pct(raw / reg.scale), lo, hi))
    if conversion is Conversion.PV_RANGE:
        lo, hi = scaling.pv_lo[index], scaling.pv_hi[index]
        return float(lo + raw * (hi - lo) / (reg.scale * 100.0))
    if conversion is Conversion.PV_SPAN:   # % of the PV range x scale -> PV units, what the loop bank takes
        return raw / (reg.scale * 100.0) * float(scaling.pv_hi[index] - scaling.pv_lo[index])
    if conversion is Conversion.FLAG:
        return bool(raw)
    if conversion in (Conversion.BITS, Conversion.COUNTER):
        return int(raw)
    if reg.zero_is_off and raw == 0:
        return math.inf
    return raw / reg.scale


def decode_write(address: int, values: Sequence[int], scaling: Scaling, index: int, *,
                 auto: bool = False, instructor: bool = False) -> list[tuple[str, Any]]:
    """Validate a write of raw ``values`` from ``address`` on unit ``index``; return the physical changes.

    Returns ``[(quantity, value), ...]`` in address order with quantity one of ``op`` (% travel), ``sp``
    (PV units), ``auto`` (bool), ``kc``, ``ti`` (s, ``inf`` = no integral), ``td`` (s), ``S``, ``J``
    (% travel), ``load`` (% flow), ``noise`` (standard deviation, PV units), ``fault`` (int, :class:`Fault`
    bits). Every register is checked before anything is returned, so a refused write changes nothing.

    Raises
    ------
    RegisterAddressError : an address outside the map.
    RegisterAccessError : read-only register; controller register on a loop without one; instructor
        register without ``instructor``; OP while the internal controller is in ``auto``.
    RegisterValueError : a raw value outside the register's range, e.g.
        ``register op_pct: 12000 out of range 0..10000``.
    """
    count = len(values)
    if count < 1 or address < 0 or address + count > N_REGISTERS:
        raise RegisterAddressError(f"holding registers {address}..{address + count - 1} outside the map "
                                   f"0..{N_REGISTERS - 1}", address=address, count=count)
    has_ctl = bool(scaling.has_controller[index])
    changes: list[tuple[str, Any]] = []
    for a, raw in zip(range(address, address + count), values):
        reg = holding_at(a)
        where = f"register {reg.name} (holding {reg.address})"
        refusal = None
        if reg.access is R:
            refusal = "is read-only"
        elif reg.access is RW_CONTROLLER and not has_ctl:
            refusal = "needs an internal controller; this loop has none"
        elif reg.access is RW_INSTRUCTOR and not instructor:
            refusal = "needs instructor write permission"
        elif reg.quantity == "op" and has_ctl and auto:
            refusal = "is writable only while the controller is in manual"
        if refusal is not None:
            raise RegisterAccessError(f"{where} {refusal}", register=reg.name)
        raw = int(raw)
        lo, hi = write_range(reg, scaling, index)
        signed = raw - 65536 if reg.type is DataType.INT16 and raw >= 32768 else raw
        if not (lo <= signed <= hi) or not (0 <= raw <= 65535):
            raise RegisterValueError(f"register {reg.name}: {signed} out of range {lo}..{hi}", register=reg.name,
                                     value=signed, allowed=(int(lo), int(hi)))
        changes.append((reg.quantity, decode_value(reg, signed, scaling, index)))
    return changes
