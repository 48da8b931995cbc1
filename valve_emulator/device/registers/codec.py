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

Every function takes the map it works on (``regmap``, default the standard map,
:data:`~valve_emulator.device.registers.mapping.STANDARD`): a configured map
(``device.register_map``) is served by these same rules, one row at a time.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Final, Protocol

import numpy as np

from valve_emulator.device.registers.errors import (
    RegisterAccessError,
    RegisterAddressError,
    RegisterValueError,
)
from valve_emulator.device.registers.mapping import STANDARD, RegisterMap
from valve_emulator.device.registers.scaling import Scaling
from valve_emulator.device.registers.table import (
    CONTROLLER_QUANTITIES,
    MAP_VERSION,
    N_REGISTERS,
    RW_CONTROLLER,
    RW_INSTRUCTOR,
    WRITABLE_QUANTITIES,
    Conversion,
    Fault,
    R,
    Register,
    Status,
    address_of,
)
from valve_emulator.device.registers.words import CDAB, DataType, float32_bits, from_words, split32, split_words

__all__ = ["WritePermission", "decode_value", "decode_write", "encode_loop", "encode_value", "encode_write",
           "loop_values", "patch", "patches", "physical_range", "status_word", "value_decoder", "value_encoder",
           "writable_by", "write_range"]

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


def _span(reg: Register, scaling: Scaling, index: int) -> tuple[float, float]:
    """The engineering range a :attr:`Conversion.COUNTS` register scales (its own, or the loop's PV range)."""
    if reg.span is not None:
        return reg.span
    return float(scaling.pv_lo[index]), float(scaling.pv_hi[index])


def _scaled(reg: Register, value: float, scaling: Scaling, index: int) -> float:
    """The unrounded raw value ``y`` of a scaled integer register (see the module docstring)."""
    return _scaler(reg, scaling, index)(value)


def _scaler(reg: Register, scaling: Scaling, index: int) -> Callable[[float], float]:
    """:func:`_scaled` of register ``reg`` on loop ``index`` as a function of the value, its constants looked up
    once (the expressions are the rule's, term for term, so every value gives the same number)."""
    conversion = reg.conversion
    if conversion is Conversion.COUNTS:
        (e_lo, e_hi), (lo, hi) = _span(reg, scaling, index), reg.counts
        return lambda value: lo + (value - e_lo) * (hi - lo) / (e_hi - e_lo)
    if conversion is Conversion.PV_RANGE:
        lo, k = _per_range(reg, scaling, index)
        return lambda value: (value - lo) * k
    if conversion is Conversion.PV_SPAN:   # a width w reads like the PV lo + w
        lo, k = _per_range(reg, scaling, index)
        return lambda value: ((lo + value) - lo) * k
    scale = reg.scale
    if conversion is Conversion.LOOP_CURRENT:
        return lambda value: scaling.op_to_ma_at(value, index) * scale
    return lambda value: value * scale


def _round_clip(y: float, lo: int, hi: int) -> int:
    """round(y) half to even, clipped to lo..hi; NaN reads as lo (bounds are integers: clip, then round)."""
    if not y >= lo:
        return lo
    if y > hi:
        return hi
    return round(y)


def _cdab(reg: Register, scaling: Scaling) -> bool:
    """Are the words of ``reg`` low word first (its own word order, else the device's)?"""
    return (reg.word_order or scaling.word_order) is CDAB


def encode_value(reg: Register, value: Any, scaling: Scaling, index: int) -> tuple[int, ...]:
    """The ``reg.width`` words register ``reg`` shows for the physical ``value`` of loop ``index``."""
    return value_encoder(reg, scaling, index)(value)


def value_encoder(reg: Register, scaling: Scaling, index: int) -> Callable[[Any], tuple[int, ...]]:
    """:func:`encode_value` of register ``reg`` on loop ``index`` as a function of the value, the register's rules
    looked up once: for a caller that encodes the same register again and again (a write's echo in the image)."""
    cdab = _cdab(reg, scaling)
    if reg.type is DataType.FLOAT32:
        return lambda value: split32(float32_bits(float(value)), cdab)
    if reg.type is DataType.FLOAT64:
        return lambda value: split_words(int.from_bytes(struct.pack(">d", float(value)), "big"), 4, cdab)
    raw = _raw_encoder(reg, scaling, index)
    if reg.width == 2:
        return lambda value: split32(raw(value) & 0xFFFFFFFF, cdab)
    return lambda value: (raw(value) & 0xFFFF,)


def _raw_encoder(reg: Register, scaling: Scaling, index: int) -> Callable[[Any], int]:
    """The raw integer an integer register shows for a value (before two's complement and word order)."""
    conversion = reg.conversion
    if conversion is Conversion.COUNTER:
        modulus = reg.type.raw_range[1] + 1
        return lambda value: int(value) % modulus
    if conversion is Conversion.BITS:
        return int
    if conversion is Conversion.FLAG:
        return lambda value: 1 if value else 0
    scaled, (lo, hi) = _scaler(reg, scaling, index), reg.read_range
    if conversion is Conversion.LINEAR and not reg.zero_is_off:   # the usual register, in one expression
        scale = reg.scale
        return lambda value: _round_clip(float(value) * scale, lo, hi)
    if reg.zero_is_off:   # 0: off (a value that is not finite and > 0)
        return lambda value: _round_clip(scaled(float(value)), lo, hi) if math.isfinite(value) and value > 0 else 0
    return lambda value: _round_clip(scaled(float(value)), lo, hi)


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


def loop_values(state: Any, index: int, *, tick: int, overruns: int, time: float) -> dict[str, Any]:
    """The physical value of every quantity of loop ``index`` (what its registers show), by quantity name.

    ``state`` is read as :func:`~valve_emulator.device.registers.kernel.encode` describes.
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
    values["controller"] = controller
    return values


def encode_loop(state: Any, scaling: Scaling, index: int, *, tick: int, overruns: int,
                time: float, regmap: RegisterMap = STANDARD) -> np.ndarray:
    """Every register of loop ``index`` in ``regmap``: int64 array (``regmap.row_words``,) of words, one
    register at a time (the standard map: its N_REGISTERS words, the compiled pass's specification).

    Registers of the internal controller (:data:`~.table.CONTROLLER_QUANTITIES`) read 0 on a loop without one.
    """
    values = loop_values(state, index, tick=tick, overruns=overruns, time=time)
    row = np.zeros(regmap.row_words, dtype=np.int64)
    for reg in regmap.registers:
        if reg.quantity in CONTROLLER_QUANTITIES and not values["controller"]:
            continue
        at = regmap.word_offset(reg.table, reg.address)
        row[at:at + reg.width] = encode_value(reg, values[reg.quantity], scaling, index)
    return row


def patch(row: np.ndarray, quantity: str, value: Any, scaling: Scaling, index: int, *,
          regmap: RegisterMap = STANDARD) -> None:
    """Overwrite, in one loop's served word ``row`` of ``regmap``, the registers that show ``quantity`` (after
    an accepted write), and the ``status`` bit the quantity flips."""
    for at, words in patches(lambda at, width: row[at:at + width], quantity, value, scaling, index, regmap=regmap):
        row[at:at + len(words)] = words


def patches(read: Callable[[int, int], Sequence[int]], quantity: str, value: Any, scaling: Scaling, index: int, *,
            regmap: RegisterMap = STANDARD) -> Iterator[tuple[int, tuple[int, ...]]]:
    """What :func:`patch` writes, as ``(word of the row, words)`` pairs, for a caller that keeps the row
    elsewhere (the device writes them straight into its byte image). ``read(word, width)`` gives the row's
    words there now; each pair must be written before the next is asked for (the ``status`` word is read
    after the quantity's own registers are written)."""
    if quantity not in WRITABLE_QUANTITIES:
        raise KeyError(f"quantity {quantity!r} is not writable")
    for reg in regmap.showing(quantity):
        yield regmap.word_offset(reg.table, reg.address), encode_value(reg, value, scaling, index)
    if quantity in _STATUS_FLAG:
        bit, is_set = _STATUS_FLAG[quantity]
        for reg in regmap.showing("status"):
            at = regmap.word_offset(reg.table, reg.address)
            status = int(from_words(read(at, reg.width), reg.type, reg.word_order or scaling.word_order))
            status = (status & ~int(bit)) | (int(bit) if is_set(value) else 0)
            yield at, encode_value(reg, status, scaling, index)


def writable_by(reg: Register, role: Any) -> bool:
    """Whether ``role`` may write register ``reg``: by its permissions, or for a client without credentials
    (``None``) every writable register but the instructor's."""
    return role.may_write(reg.quantity) if role is not None else reg.access is not RW_INSTRUCTOR


def write_range(reg: Register, scaling: Scaling, index: int) -> tuple[int, int]:
    """Raw range a write to ``reg`` may take on loop ``index`` (OP registers: within the loop's op_limits)."""
    if reg.conversion is Conversion.COUNTS:
        lo, hi = reg.write
        if reg.quantity == "op":   # the counts of the loop's op_limits, inside the configured raw range
            ends = sorted(_scaled(reg, float(x), scaling, index) for x in scaling.op_limits[index])
            lo, hi = max(lo, math.ceil(ends[0] - 1e-9)), min(hi, math.floor(ends[1] + 1e-9))
        return int(lo), int(hi)
    if reg.quantity != "op":
        return reg.write
    ranges = scaling.ma_raw_range if reg.conversion is Conversion.LOOP_CURRENT else scaling.op_raw_range
    return tuple(ranges[index])


def physical_range(quantity: str, scaling: Scaling, index: int) -> tuple[float, float]:
    """The physical values a write of ``quantity`` may take on loop ``index``: those its standard register
    accepts (so a float or counts tag of a configured map allows exactly what the standard map does)."""
    reg = STANDARD.written(quantity)
    lo, hi = write_range(reg, scaling, index)
    if reg.zero_is_off:
        lo = max(lo, 1)
    ends = sorted((float(decode_value(reg, lo, scaling, index)), float(decode_value(reg, hi, scaling, index))))
    return ends[0], ends[1]


def decode_value(reg: Register, raw: int, scaling: Scaling, index: int) -> Any:
    """The physical value of a written raw word (``raw`` signed for ``int16``); inverse of :func:`encode_value`."""
    return value_decoder(reg, scaling, index)(raw)


def value_decoder(reg: Register, scaling: Scaling, index: int) -> Callable[[int], Any]:
    """:func:`decode_value` of register ``reg`` on loop ``index`` as a function of the raw word, its rules looked
    up once (the expressions are the rule's, term for term)."""
    conversion = reg.conversion
    if conversion is Conversion.COUNTS:
        (e_lo, e_hi), (lo, hi) = _span(reg, scaling, index), reg.counts
        return lambda raw: e_lo + (raw - lo) * (e_hi - e_lo) / (hi - lo)
    scale = reg.scale
    if conversion is Conversion.LOOP_CURRENT:
        (lo, hi), table = scaling.op_limits[index], scaling.tables[index]
        return lambda raw: float(np.clip(table.to_pct(raw / scale), lo, hi))
    if conversion is Conversion.PV_RANGE:
        lo, hi = scaling.pv_lo[index], scaling.pv_hi[index]
        return lambda raw: float(lo + raw * (hi - lo) / (scale * 100.0))
    if conversion is Conversion.PV_SPAN:   # % of the PV range x scale -> PV units, what the loop bank takes
        return lambda raw: raw / (scale * 100.0) * float(scaling.pv_hi[index] - scaling.pv_lo[index])
    if conversion is Conversion.FLAG:
        return bool
    if conversion in (Conversion.BITS, Conversion.COUNTER):
        return int
    if reg.zero_is_off:
        return lambda raw: math.inf if raw == 0 else raw / scale
    return lambda raw: raw / scale


class WritePermission(Protocol):
    """What a client may write: a :class:`~valve_emulator.device.roles.Role` (the permission table)."""

    name: str

    def may_write(self, quantity: str) -> bool: ...


def decode_write(address: int, values: Sequence[int], scaling: Scaling, index: int, *,
                 role: WritePermission | None = None, auto: bool = False, regmap: RegisterMap = STANDARD
                 ) -> list[tuple[str, Any]]:
    """Validate a write of raw holding-register ``values`` from ``address`` on unit ``index`` of ``regmap``
    by a client of ``role``; return the physical changes.

    Returns ``[(quantity, value), ...]`` in address order with quantity one of ``op`` (% travel), ``sp``
    (PV units), ``auto`` (bool), ``kc``, ``ti`` (s, ``inf`` = no integral), ``td`` (s), ``S``, ``J``
    (% travel), ``load`` (% flow), ``noise`` (standard deviation, PV units), ``fault`` (int, :class:`Fault`
    bits). Every register is checked before anything is returned, so a refused write changes nothing. A
    register of two or four words is written whole, all its words in one request.

    Raises
    ------
    RegisterAddressError : an address outside the map, or part of a wider register.
    RegisterAccessError : read-only register; controller register on a loop without one; a register
        ``role`` may not write (None: a client without credentials, which writes every register except the
        ``RW-instructor`` ones: :data:`~valve_emulator.device.roles.UNAUTHENTICATED`); OP while the internal
        controller is in ``auto``.
    RegisterValueError : a raw value outside the register's range, e.g.
        ``register op_pct: 12000 out of range 0..10000``.
    """
    count = len(values)
    if regmap.standard and (count < 1 or address < 0 or address + count > N_REGISTERS):
        raise RegisterAddressError(f"holding registers {address}..{address + count - 1} outside the map "
                                   f"0..{N_REGISTERS - 1}", address=address, count=count)
    if count < 1 or any(regmap.row_at("holding", a) is None for a in range(address, address + count)):
        missing = next((a for a in range(address, address + count) if regmap.row_at("holding", a) is None),
                       address)
        raise RegisterAddressError(f"holding registers {address}..{address + count - 1}: no tag at holding "
                                   f"{missing} ({regmap.reference('holding', missing)})", address=address,
                                   count=count)
    has_ctl = bool(scaling.has_controller[index])
    changes: list[tuple[str, Any]] = []
    a = address
    while a < address + count:
        reg = regmap.row_at("holding", a)
        where = f"register {reg.name} (holding {reg.address})"
        refusal = None
        if reg.access is R:
            refusal = "is read-only"
        elif reg.access is RW_CONTROLLER and not has_ctl:
            refusal = "needs an internal controller; this loop has none"
        elif not writable_by(reg, role):
            refusal = "is not writable by role " + repr("unauthenticated" if role is None else role.name)
        elif reg.quantity == "op" and has_ctl and auto:
            refusal = "is writable only while the controller is in manual"
        elif reg.address != a or reg.address + reg.width > address + count:
            raise RegisterAddressError(f"{where} takes holding {reg.address}..{reg.address + reg.width - 1}: "
                                       f"write all its {reg.width} registers at once", address=address,
                                       count=count)
        if refusal is not None:
            raise RegisterAccessError(f"{where} {refusal}", register=reg.name)
        words = [int(w) for w in values[a - address:a - address + reg.width]]
        changes.append((reg.quantity, _decode_words(reg, words, scaling, index)))
        a += reg.width
    return changes


def _decode_words(reg: Register, words: list[int], scaling: Scaling, index: int) -> Any:
    """The checked physical value of the words a client wrote to ``reg``."""
    if not all(0 <= w <= 65535 for w in words):
        raise RegisterValueError(f"register {reg.name}: {words} are not 16-bit words", register=reg.name,
                                 value=words[0], allowed=(0, 65535))
    if reg.type.is_float:
        value = float(from_words(words, reg.type, reg.word_order or scaling.word_order))
        return _within_physical(reg, value, scaling, index, shown=f"{value:g}")
    raw = int(from_words(words, reg.type, reg.word_order or scaling.word_order))
    lo, hi = write_range(reg, scaling, index)
    if not lo <= raw <= hi:
        raise RegisterValueError(f"register {reg.name}: {raw} out of range {lo}..{hi}", register=reg.name,
                                 value=raw, allowed=(int(lo), int(hi)))
    value = decode_value(reg, raw, scaling, index)
    if reg.conversion is Conversion.COUNTS:
        return _within_physical(reg, value, scaling, index, shown=str(raw))
    return value


def _within_physical(reg: Register, value: float, scaling: Scaling, index: int, *, shown: str) -> float:
    """``value`` if the standard register of its quantity would accept it (ends within rounding), else
    :class:`RegisterValueError` naming ``reg``."""
    lo, hi = physical_range(reg.quantity, scaling, index)
    slack = 1e-9 * max(1.0, abs(lo), abs(hi))
    standard = STANDARD.written(reg.quantity)
    if standard.zero_is_off and value == 0:
        return math.inf
    if not (math.isfinite(value) and lo - slack <= value <= hi + slack):
        raise RegisterValueError(f"register {reg.name}: {shown} out of range ({value:g} outside {lo:g}..{hi:g} "
                                 f"{standard.units})", register=reg.name, value=value, allowed=(lo, hi))
    return min(max(value, lo), hi)
