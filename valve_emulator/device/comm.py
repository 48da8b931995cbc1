"""Communication faults on demand: a unit that stops answering, answers late, says it is busy, or hangs up.

Pure (no pymodbus, no asyncio). Every unit id has two *unit registers* beside its loops' blocks, in the
holding table at fixed addresses (:data:`UNIT_REGISTERS`)::

    comm_fault     holding 65280 (0xFF00, 465281)   0 none, 1 no response, 2 exception 0x06 server busy,
                                                     3 exception 0x04 server failure, 4 close the connection,
                                                     5 corrupt the CRC (RTU framings; Modbus TCP answers)
    comm_delay_ms  holding 65281 (0xFF01, 465282)   added response latency, 0..10,000 ms

Both are instructor registers (written by a role that lists them, :mod:`~valve_emulator.device.roles`, like ``S``,
``J`` and ``fault``) and readable by anyone. A request that reads or writes them is always carried out and
answered at once, whatever fault is active, so a test rig can clear a fault over the wire; every other
request of the unit suffers the fault. A unit with more than 2040 loops' blocks covers these addresses
with its loops' registers and has no unit registers over the wire (scenario events still set them).

:class:`CommFaults` keeps the state of every unit; the Modbus adapters ask it :meth:`CommFaults.plan` per
request.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

from valve_emulator.device.registers import (
    BLOCK_STRIDE,
    COMM_BASE,
    UNIT_REGISTERS,
    CommFault,
    RegisterAccessError,
    RegisterAddressError,
    RegisterValueError,
)

__all__ = ["CommFaults", "CommState"]

_END: Final = COMM_BASE + len(UNIT_REGISTERS)


@dataclass(slots=True)
class CommState:
    """One unit's communication fault: ``fault`` and the added latency ``delay_ms``."""

    fault: CommFault = CommFault.NONE
    delay_ms: int = 0

    @property
    def words(self) -> tuple[int, int]:
        return int(self.fault), int(self.delay_ms)


class CommFaults:
    """The communication faults of the units ``blocks`` (unit id -> number of loop blocks) describes."""

    def __init__(self, blocks: dict[int, int]) -> None:
        self._blocks = dict(blocks)
        self._state: dict[int, CommState] = {u: CommState() for u in blocks}
        #: units with a fault or a delay now (the adapters' fast path: empty means nothing to do)
        self.active: set[int] = set()

    def state(self, unit: int) -> CommState:
        return self._state[unit]

    def served(self, unit: int) -> bool:
        """Does ``unit`` answer the unit registers over the wire (its blocks end below them)?"""
        return BLOCK_STRIDE * self._blocks[unit] <= COMM_BASE

    def covers(self, unit: int, address: int) -> bool:
        """Is holding ``address`` of ``unit`` one of the unit registers (or past the map, beside them)?"""
        return address >= COMM_BASE and self.served(unit)

    def set(self, unit: int, *, fault: int | None = None, delay_ms: int | None = None) -> None:
        """Set the fault and/or the delay of ``unit`` (values checked like a register write)."""
        words = list(self._state[unit].words)
        if fault is not None:
            words[0] = fault
        if delay_ms is not None:
            words[1] = delay_ms
        self._apply(unit, self._check(COMM_BASE, words))

    def read(self, unit: int, address: int, count: int) -> bytes:
        """The big-endian words of ``count`` unit registers from ``address``; RegisterAddressError outside."""
        if not (address >= COMM_BASE and address + count <= _END and count >= 1):
            raise RegisterAddressError(f"holding registers {address}..{address + count - 1} outside the unit "
                                       f"registers {COMM_BASE}..{_END - 1}", address=address, count=count)
        words = self._state[unit].words[address - COMM_BASE:address - COMM_BASE + count]
        return b"".join(w.to_bytes(2, "big") for w in words)

    def write(self, unit: int, address: int, values: Sequence[int], *, role: Any) -> None:
        """A write of unit registers by a client of ``role`` (:class:`~valve_emulator.device.roles.Role`);
        checked whole before anything changes (RegisterError)."""
        if not (address >= COMM_BASE and address + len(values) <= _END and values):
            raise RegisterAddressError(f"holding registers {address}..{address + len(values) - 1} outside the "
                                       f"unit registers {COMM_BASE}..{_END - 1}", address=address,
                                       count=len(values))
        for reg in UNIT_REGISTERS[address - COMM_BASE:address - COMM_BASE + len(values)]:
            if not role.may_write(reg.quantity):
                raise RegisterAccessError(f"register {reg.name} (holding {reg.address}) is not writable by role "
                                          f"{role.name!r}", register=reg.name)
        words = list(self._state[unit].words)
        words[address - COMM_BASE:address - COMM_BASE + len(values)] = values
        self._apply(unit, self._check(address, values, words))

    @staticmethod
    def _check(address: int, values: Sequence[int], words: Sequence[int] | None = None) -> list[int]:
        for reg, raw in zip(UNIT_REGISTERS[address - COMM_BASE:], values):
            lo, hi = reg.write
            if not lo <= int(raw) <= hi:
                raise RegisterValueError(f"register {reg.name}: {int(raw)} out of range {lo}..{hi}",
                                         register=reg.name, value=int(raw), allowed=(lo, hi))
        return list(values if words is None else words)

    def _apply(self, unit: int, words: list[int]) -> None:
        state = self._state[unit]
        state.fault, state.delay_ms = CommFault(words[0]), int(words[1])
        if state.fault or state.delay_ms:
            self.active.add(unit)
        else:
            self.active.discard(unit)

    def targets(self, unit: int, pdu: bytes) -> bool:
        """Does request ``pdu`` read or write the unit registers (FC 3, 6, 16, 22 starting at one, or FC23
        reading or writing them)?"""
        if len(pdu) >= 3 and pdu[0] in (3, 6, 16, 22, 23) and self.covers(unit, (pdu[1] << 8) | pdu[2]):
            return True
        return len(pdu) >= 7 and pdu[0] == 23 and self.covers(unit, (pdu[5] << 8) | pdu[6])

    def plan(self, unit: int, pdu: bytes) -> CommState | None:
        """The fault to apply to request ``pdu`` of ``unit``; ``None``: answer it normally."""
        if unit not in self.active or unit not in self._state or self.targets(unit, pdu):
            return None
        return self._state[unit]
