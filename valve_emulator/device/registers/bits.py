"""The bit tables: coils (function codes 1, 5, 15) and discrete inputs (function code 2).

Pure (no numpy, no pymodbus). Every bit is a view of a register of the map, so the bit tables add no state
and no rule of their own:

- a *discrete input* is one bit of the ``status`` register (:class:`~.table.Status`): discrete input ``k``
  is status bit ``k``;
- a *coil* reads one status bit and writes a 16-bit register with 0 or 1 (``auto`` writes ``mode``,
  ``seized`` writes ``fault``), so a coil write is checked exactly like the register write it stands for
  (access, controller present, instructor permission) and refused with the same error.

Addresses are zero-based PDU addresses inside a loop's block; a unit with several loops puts loop ``k``'s
bits at ``32k + address`` like its registers (:data:`~.table.BLOCK_STRIDE`). One-based references (what an
HMI tag editor shows) put the table's digit in front of ``address + 1``: ``0xxxx`` coils, ``1xxxx``
discrete inputs, ``3xxxx`` input and ``4xxxx`` holding registers (:func:`reference`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Final

from valve_emulator.config.register_map import reference  # the one-based references of every table
from valve_emulator.device.registers.errors import RegisterAddressError
from valve_emulator.device.registers.table import (
    BLOCK_STRIDE,
    RW_CONTROLLER,
    RW_INSTRUCTOR,
    Access,
    R,
    Status,
    address_of,
)

__all__ = ["BITS", "COILS", "DISCRETE_INPUTS", "Bit", "BitTable", "bit_values", "check_bits", "coil_write",
           "reference"]


class BitTable(StrEnum):
    """The two single-bit tables of the Modbus data model."""

    COIL = "coil"                       # read FC1, write FC5 / FC15
    DISCRETE_INPUT = "discrete_input"   # read FC2


@dataclass(frozen=True, slots=True, kw_only=True)
class Bit:
    """One coil or discrete input.

    Parameters
    ----------
    name, table, address : its name, :class:`BitTable` and zero-based address inside a loop's block.
    status : the bit of the ``status`` register it reads.
    access : :class:`~.table.Access` of the register a write goes to (``R`` for discrete inputs).
    register : the holding register a coil write sets to 0 or 1 (``None`` for discrete inputs).
    meaning : what 1 means, for the documentation.
    """

    name: str
    table: BitTable
    address: int
    status: Status
    access: Access
    register: str | None = None
    meaning: str = ""


_MEANING: Final = {
    Status.STUCK: "valve at rest",
    Status.MOVING: "valve moving",
    Status.SAT_LOW: "OP clipped at 0 %",
    Status.SAT_HIGH: "OP clipped at 100 %",
    Status.CONTROLLER: "internal controller present",
    Status.AUTO: "controller in auto",
    Status.SEIZED: "valve seized (fault bit 0)",
}

DISCRETE_INPUTS: Final[tuple[Bit, ...]] = tuple(
    Bit(name=s.name.lower(), table=BitTable.DISCRETE_INPUT, address=s.bit_length() - 1, status=s, access=R,
        meaning=_MEANING[s]) for s in Status)
COILS: Final[tuple[Bit, ...]] = (
    Bit(name="auto", table=BitTable.COIL, address=0, status=Status.AUTO, access=RW_CONTROLLER, register="mode",
        meaning="1 auto, 0 manual"),
    Bit(name="seized", table=BitTable.COIL, address=1, status=Status.SEIZED, access=RW_INSTRUCTOR,
        register="fault", meaning="1 seizes the valve (fault)"),
)
BITS: Final = {BitTable.COIL: COILS, BitTable.DISCRETE_INPUT: DISCRETE_INPUTS}
assert all(b.address == i for bits in BITS.values() for i, b in enumerate(bits))  # dense from 0
assert all(len(bits) <= BLOCK_STRIDE for bits in BITS.values())


def check_bits(table: BitTable, address: int, count: int, *, blocks: int = 1) -> tuple[int, int]:
    """``(block, offset)`` of ``count`` bits from ``address``; :class:`RegisterAddressError` unless all exist.

    A request stays inside one loop's block (bits ``32k .. 32k + n − 1`` of loop ``k``).
    """
    bits = BITS[table]
    block, offset = divmod(address, BLOCK_STRIDE)
    if count < 1 or address < 0 or block >= blocks or offset + count > len(bits):
        span = f"{table.value} {address}..{address + count - 1}"
        where = (f"0..{len(bits) - 1}" if blocks == 1 else
                 f"{BLOCK_STRIDE}k..{BLOCK_STRIDE}k+{len(bits) - 1}, k = 0..{blocks - 1}")
        raise RegisterAddressError(f"{span} outside the {table.value} table {where}", address=address,
                                   count=count)
    return block, offset


def bit_values(table: BitTable, status: int, offset: int, count: int) -> list[bool]:
    """The values of ``count`` bits from ``offset`` of one loop whose ``status`` register reads ``status``."""
    return [bool(status & b.status) for b in BITS[table][offset:offset + count]]


def coil_write(offset: int, on: bool) -> tuple[int, int]:
    """``(holding address, raw value)`` a write of coil ``offset`` stands for (checked by the register map)."""
    return address_of(str(COILS[offset].register)), int(on)
