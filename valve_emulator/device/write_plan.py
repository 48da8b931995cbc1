"""A one-register write, checked and shown from what was worked out for its address once.

A Modbus client (a lockstep test bench writing OP every scan, a SCADA writing set points) writes the same
few registers of the same loops again and again. :func:`~valve_emulator.device.registers.decode_write` finds
the register row, checks the register's access, the role, the controller's mode and the value's range, and
:func:`~valve_emulator.device.registers.patches` finds the registers that show the quantity, at every write.
A :class:`WritePlan` holds what of that depends only on the loop and the address -- the row, the raw range,
the byte offsets of the registers that show the quantity -- so a
write that is accepted costs the role's check, the value's decoding and the encoding of those registers.

A plan only ever *accepts*: a write it does not accept (refused by the role, OP while the controller is in
``auto``, a word outside the range) goes the general way, which refuses it with the same error and message
as without plans. Writes that a plan does not cover at all (several registers, 32-bit and float registers,
counts scaled to an engineering span, quantities that flip a ``status`` bit) go the general way too.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from valve_emulator.device.registers import (
    RW_CONTROLLER,
    Conversion,
    DataType,
    R,
    Register,
    Scaling,
    value_decoder,
    value_encoder,
    writable_by,
    write_range,
)
from valve_emulator.device.registers.mapping import RegisterMap

__all__ = ["WritePlan", "write_plan"]

#: Quantities whose write also flips a bit of the ``status`` register: read-modify-write, the general way.
_FLIPS_STATUS = frozenset({"auto", "fault"})
_ONE_WORD = (DataType.UINT16, DataType.INT16)


@dataclass(frozen=True)
class WritePlan:
    """The accepted write of one word to register :attr:`register` of loop :attr:`index`.

    ``shows`` holds, for each image the write is shown in, the byte offset of the loop's row there and, for
    every register that shows the quantity, the word of the row it starts at, the :mod:`struct` format of its
    words and its :func:`~valve_emulator.device.registers.value_encoder`.
    """

    index: int
    register: Register
    low: int                 # the raw range a write may take on this loop
    high: int
    manual_only: bool        # OP of a loop with a controller: refused while the controller is in auto
    decode: Callable[[int], Any]   # the raw word's physical value (value_decoder)
    shows: tuple[tuple[bytearray, int, tuple[tuple[int, str, Callable[[Any], tuple[int, ...]]], ...]], ...]

    @property
    def quantity(self) -> str:
        return self.register.quantity

    def accept(self, word: int, role: Any, auto: Callable[[int], bool]) -> Any:
        """The physical value the write of ``word`` by ``role`` sets, or ``None`` where the general way must
        judge it (it may refuse). ``auto(index)`` tells whether the loop's controller is in auto (asked only for
        OP of a loop with a controller)."""
        if not writable_by(self.register, role):
            return None
        if self.manual_only and auto(self.index):
            return None
        if not 0 <= word <= 0xFFFF:
            return None
        raw = word - 0x10000 if self.register.type is DataType.INT16 and word >= 0x8000 else word
        if not self.low <= raw <= self.high:
            return None
        return self.decode(raw)

    def show(self, value: float) -> None:
        """Write the words of every register showing the quantity's new ``value`` into the images."""
        for image, start, registers in self.shows:
            for at, words, encoder in registers:
                struct.pack_into(words, image, start + 2 * at, *encoder(value))


def write_plan(maps: tuple[tuple[RegisterMap, bytearray, int], ...], regmap: RegisterMap, scaling: Scaling,
               index: int, address: int) -> WritePlan | None:
    """The plan of a one-word write at holding ``address`` of ``regmap`` on loop ``index``, ``None`` where
    the general way must judge every such write (see the module docstring). ``maps`` are the images the
    device shows writes in: ``(register map, image, byte offset of the loop's row)``."""
    reg = regmap.row_at("holding", address)
    if (reg is None or reg.address != address or reg.type not in _ONE_WORD or reg.access is R
            or reg.quantity in _FLIPS_STATUS or reg.conversion is Conversion.COUNTS):
        return None
    has_ctl = bool(scaling.has_controller[index])
    if reg.access is RW_CONTROLLER and not has_ctl:
        return None
    shows = []
    for shown_map, image, start in maps:
        registers = tuple((shown_map.word_offset(r.table, r.address), f">{r.width}H", value_encoder(r, scaling, index))
                          for r in shown_map.showing(reg.quantity))
        shows.append((image, start, registers))
    low, high = write_range(reg, scaling, index)
    return WritePlan(index=index, register=reg, low=int(low), high=int(high),
                     manual_only=reg.quantity == "op" and has_ctl,
                     decode=value_decoder(reg, scaling, index), shows=tuple(shows))

