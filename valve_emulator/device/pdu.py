"""The structure of the request PDUs the device serves, checked on raw bytes before anything decodes them.

Pure code (no pymodbus, no exception codes: the adapter in :mod:`~valve_emulator.device.server` decides how
to answer). Function codes and limits follow the *Modbus Application Protocol Specification V1.1b3*
(§6.1 read coils, §6.2 read discrete inputs, §6.3 read holding registers, §6.4 read input registers,
§6.5 write single coil, §6.6 write single register, §6.8 diagnostics, §6.11 write multiple coils, §6.12
write multiple registers, §6.16 mask write register, §6.17 read/write multiple registers, §6.21 read
device identification)::

    FC  PDU layout (big-endian 16-bit fields)                         quantity limits
    1   fc | address | count                      (5 bytes)           count 1..2000
    2   fc | address | count                      (5 bytes)           count 1..2000
    3   fc | address | count                      (5 bytes)           count 1..125
    4   fc | address | count                      (5 bytes)           count 1..125
    5   fc | address | value                      (5 bytes)           value 0xFF00 (on) or 0x0000 (off)
    6   fc | address | value                      (5 bytes)           -
    8   fc | sub-function | data...                (3 + data)          sub-function 0: any data;
                                                                       0x0A..0x0E: data 0x0000
    15  fc | address | count | bytes | bits...     (6 + bytes)         count 1..1968, bytes = ceil(count/8)
    16  fc | address | count | bytes | values...   (6 + bytes)         count 1..123, bytes = 2·count
    23  fc | read addr | read count | write addr | write count | bytes | values...   (10 + bytes)
                                                                       read 1..125, write 1..121, bytes = 2·write
    22  fc | address | and mask | or mask          (7 bytes)           -
    43  fc | MEI type 0x0E | read code | object id (4 bytes)           read code 1..4

A PDU that breaks these rules is *malformed*: the specification answers it with exception 0x03 (illegal
data value) before it looks at any address.
"""

from __future__ import annotations

from typing import Final

from valve_emulator.device.registers import REGISTERS

__all__ = ["BIT_READ_FUNCTIONS", "BIT_WRITE_FUNCTIONS", "COUNTER_SUBFUNCTIONS", "MAX_BITS_READ",
           "MAX_BITS_WRITE", "MAX_READ", "MAX_WRITE", "MEI_DEVICE_ID", "READ_FUNCTIONS", "WRITE_FUNCTIONS",
           "malformed", "register_names", "write_target"]

READ_FUNCTIONS: Final = frozenset({3, 4})
WRITE_FUNCTIONS: Final = frozenset({6, 16, 23, 22})     # register writes
BIT_READ_FUNCTIONS: Final = frozenset({1, 2})
BIT_WRITE_FUNCTIONS: Final = frozenset({5, 15})
MAX_READ: Final = 125                      # registers per read (FC3, FC4, the read half of FC23)
MAX_WRITE: Final = {16: 123, 23: 121}      # registers per write: the PDU must fit in 253 bytes
MAX_BITS_READ: Final = 2000                # bits per read (FC1, FC2)
MAX_BITS_WRITE: Final = 1968               # bits per write (FC15)
MEI_DEVICE_ID: Final = 0x0E                # FC43's MEI type for read device identification
#: FC8 sub-functions answered besides 0 (return query data): clear counters and the four counters.
COUNTER_SUBFUNCTIONS: Final = frozenset(range(0x0A, 0x0F))


_FIXED_LENGTH: Final = {1: 5, 2: 5, 3: 5, 4: 5, 5: 5, 6: 5, 22: 7, 43: 4}   # PDU bytes, function code included


def _u16(pdu: bytes, at: int) -> int:
    return (pdu[at] << 8) | pdu[at + 1]


def malformed(fc: int, pdu: bytes) -> str | None:
    """Why the request ``pdu`` (function-code byte first) is not well formed for ``fc``; ``None`` if it is.

    For the function codes in the ``*_FUNCTIONS`` sets and 8, 43. Trailing bytes after a complete PDU are
    malformed too: the MBAP length then disagrees with the request. An FC8 sub-function or FC43 MEI type
    the device does not offer is not malformed (the adapter answers it as an illegal function).
    """
    n = len(pdu)
    if fc == 43 and n >= 2 and pdu[1] != MEI_DEVICE_ID:
        return None   # another MEI type (CANopen 0x0D): not offered, whatever its length
    fixed = _FIXED_LENGTH.get(fc)
    if fixed is not None and n != fixed:
        return f"function code {fc} needs a {fixed}-byte PDU, got {n}"
    if fc in READ_FUNCTIONS:
        count = _u16(pdu, 3)
        return None if 1 <= count <= MAX_READ else f"read count {count} outside 1..{MAX_READ}"
    if fc == 6:
        return None
    if fc in BIT_READ_FUNCTIONS and not 1 <= _u16(pdu, 3) <= MAX_BITS_READ:
        return f"bit count {_u16(pdu, 3)} outside 1..{MAX_BITS_READ}"
    if fc == 5 and _u16(pdu, 3) not in (0x0000, 0xFF00):
        return f"coil value 0x{_u16(pdu, 3):04X} is neither 0xFF00 (on) nor 0x0000 (off)"
    if fc == 43 and pdu[1] == MEI_DEVICE_ID and not 1 <= pdu[2] <= 4:
        return f"read device id code {pdu[2]} outside 1..4"
    if fixed is not None:
        return None
    if fc == 8:
        if n < 3:
            return f"function code 8 needs at least 3 PDU bytes, got {n}"
        if _u16(pdu, 1) in COUNTER_SUBFUNCTIONS and pdu[3:] != b"\x00\x00":
            return f"diagnostics sub-function 0x{_u16(pdu, 1):04X} needs the data field 0x0000"
        return None
    if fc == 15:
        if n < 6:
            return f"function code 15 needs at least 6 PDU bytes, got {n}"
        count, nbytes = _u16(pdu, 3), pdu[5]
        if not (1 <= count <= MAX_BITS_WRITE and nbytes == (count + 7) // 8 == n - 6):
            return (f"coil count {count}, byte count {nbytes} and {n - 6} data bytes disagree "
                    f"(count 1..{MAX_BITS_WRITE}, byte count = ceil(count / 8) = data bytes)")
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
    """``(address, count)`` of the registers (coils for FC 5, 15) a well-formed write PDU writes."""
    if fc in (5, 6, 22):
        return _u16(pdu, 1), 1
    if fc in (15, 16):
        return _u16(pdu, 1), _u16(pdu, 3)
    return _u16(pdu, 5), _u16(pdu, 7)


def register_names(address: int, count: int) -> list[str]:
    """Names of the holding registers overlapping addresses ``address .. address + count - 1``."""
    return [r.name for r in REGISTERS if r.address < address + count and address < r.address + r.width]
