"""The structure of the request PDUs the device serves, checked on raw bytes before anything decodes them.

Pure code (no pymodbus, no exception codes: the adapter in :mod:`~valve_emulator.device.server` decides how
to answer). Function codes and limits follow the *Modbus Application Protocol Specification V1.1b3*
(§6.3 read holding registers, §6.4 read input registers, §6.6 write single register, §6.12 write
multiple registers, §6.17 read/write multiple registers)::

    FC  PDU layout (big-endian 16-bit fields)                         quantity limits
    3   fc | address | count                      (5 bytes)           count 1..125
    4   fc | address | count                      (5 bytes)           count 1..125
    6   fc | address | value                      (5 bytes)           -
    16  fc | address | count | bytes | values...   (6 + bytes)         count 1..123, bytes = 2·count
    23  fc | read addr | read count | write addr | write count | bytes | values...   (10 + bytes)
                                                                       read 1..125, write 1..121, bytes = 2·write

A PDU that breaks these rules is *malformed*: the specification answers it with exception 0x03 (illegal
data value) before it looks at any address.
"""

from __future__ import annotations

from typing import Final

from valve_emulator.device.registers import REGISTERS

__all__ = ["MAX_READ", "MAX_WRITE", "READ_FUNCTIONS", "WRITE_FUNCTIONS", "malformed", "register_names",
           "write_target"]

READ_FUNCTIONS: Final = frozenset({3, 4})
WRITE_FUNCTIONS: Final = frozenset({6, 16, 23})
MAX_READ: Final = 125                      # registers per read (FC3, FC4, the read half of FC23)
MAX_WRITE: Final = {16: 123, 23: 121}      # registers per write: the PDU must fit in 253 bytes


def _u16(pdu: bytes, at: int) -> int:
    return (pdu[at] << 8) | pdu[at + 1]


def malformed(fc: int, pdu: bytes) -> str | None:
    """Why the request ``pdu`` (function-code byte first) is not well formed for ``fc``; ``None`` if it is.

    Only for the function codes in :data:`READ_FUNCTIONS` and :data:`WRITE_FUNCTIONS`. Trailing bytes
    after a complete PDU are malformed too: the MBAP length then disagrees with the request.
    """
    n = len(pdu)
    if fc in READ_FUNCTIONS or fc == 6:
        if n != 5:
            return f"function code {fc} needs a 5-byte PDU, got {n}"
        if fc != 6 and not 1 <= _u16(pdu, 3) <= MAX_READ:
            return f"read count {_u16(pdu, 3)} outside 1..{MAX_READ}"
        return None
    header = 6 if fc == 16 else 10
    if n < header:
        return f"function code {fc} needs at least {header} PDU bytes, got {n}"
    if fc == 23 and not 1 <= _u16(pdu, 3) <= MAX_READ:
        return f"read count {_u16(pdu, 3)} outside 1..{MAX_READ}"
    count, nbytes = _u16(pdu, header - 3), pdu[header - 1]
    if not (1 <= count <= MAX_WRITE[fc] and nbytes == 2 * count == n - header):
        return (f"write count {count}, byte count {nbytes} and {n - header} data bytes disagree "
                f"(count 1..{MAX_WRITE[fc]}, byte count = 2 x count = data bytes)")
    return None


def write_target(fc: int, pdu: bytes) -> tuple[int, int]:
    """``(address, count)`` of the registers a well-formed write PDU (FC 6, 16 or 23) writes."""
    if fc == 6:
        return _u16(pdu, 1), 1
    if fc == 16:
        return _u16(pdu, 1), _u16(pdu, 3)
    return _u16(pdu, 5), _u16(pdu, 7)


def register_names(address: int, count: int) -> list[str]:
    """Names of the holding registers overlapping addresses ``address .. address + count - 1``."""
    return [r.name for r in REGISTERS if r.address < address + count and address < r.address + r.width]
