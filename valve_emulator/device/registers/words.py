"""Register words: the data types a register can hold and the word order of 32-bit values.

Pure (standard library only, no pymodbus). Every 16-bit word travels big-endian (Modbus); a 32-bit value
(``uint32``, ``int32``, ``float32``) takes two consecutive registers, in the device's :class:`WordOrder`::

    value 0x12345678   ABCD: [0x1234, 0x5678]   (high word at the lower address, mbpoll -B)
                       CDAB: [0x5678, 0x1234]   (low word first, mbpoll's default)

:func:`split32` is the one place that orders the two words: the compiled image encoder compiles this same
function, and the Python codec and the clients call it, so they cannot disagree.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from enum import StrEnum
from typing import Final

from valve_emulator.config.schema import WordOrder

__all__ = ["ABCD", "CDAB", "DataType", "WordOrder", "as_word_order", "float32_bits", "from_words", "split32",
           "to_words"]

ABCD: Final = WordOrder.ABCD
CDAB: Final = WordOrder.CDAB


class DataType(StrEnum):
    """What a register (or a pair of registers) holds."""

    UINT16 = "uint16"
    INT16 = "int16"       # two's complement
    UINT32 = "uint32"     # two registers, in the word order
    INT32 = "int32"       # two registers, two's complement
    FLOAT32 = "float32"   # two registers, IEEE 754 single precision

    @property
    def width(self) -> int:
        """Number of 16-bit registers."""
        return _LAYOUT[self][0]

    @property
    def struct_format(self) -> str:
        """:mod:`struct` format of the value, big-endian (high word first)."""
        return _LAYOUT[self][1]

    @property
    def raw_range(self) -> tuple[int, int] | None:
        """Smallest and largest integer the type holds (``None`` for ``float32``)."""
        return _LAYOUT[self][2]


_LAYOUT: Final = {
    DataType.UINT16: (1, ">H", (0, 0xFFFF)),
    DataType.INT16: (1, ">h", (-0x8000, 0x7FFF)),
    DataType.UINT32: (2, ">I", (0, 0xFFFFFFFF)),
    DataType.INT32: (2, ">i", (-0x80000000, 0x7FFFFFFF)),
    DataType.FLOAT32: (2, ">f", None),
}


def as_word_order(value: str) -> WordOrder:
    """``value`` as a :class:`WordOrder`; ``ValueError`` naming it when it is neither ABCD nor CDAB."""
    try:
        return WordOrder(value)
    except ValueError:
        raise ValueError(f"word_order must be ABCD or CDAB, got {value!r}") from None


def split32(bits: int, cdab: bool) -> tuple[int, int]:
    """The two register words ``(first, second)`` of the 32-bit pattern ``bits`` (0 .. 2³²−1).

    ``cdab`` false: ABCD, the high word first; true: CDAB, the low word first.
    """
    high, low = bits >> 16, bits & 0xFFFF
    return (low, high) if cdab else (high, low)


def to_words(value: float, type_: DataType | str, order: WordOrder | str = ABCD) -> list[int]:
    """Register words of ``value`` stored as ``type_`` (integers must fit the type; floats are rounded to
    float32). ``struct.error`` when an integer does not fit."""
    type_ = DataType(type_)
    packed = struct.pack(type_.struct_format, value)
    if type_.width == 1:
        return [struct.unpack(">H", packed)[0]]
    return list(split32(struct.unpack(">I", packed)[0], WordOrder(order) is CDAB))


def from_words(words: Sequence[int], type_: DataType | str, order: WordOrder | str = ABCD) -> float:
    """The value that the first ``type_.width`` register ``words`` hold (inverse of :func:`to_words`)."""
    type_ = DataType(type_)
    if type_.width == 1:
        return struct.unpack(type_.struct_format, struct.pack(">H", int(words[0])))[0]
    # the order is an involution: applying it to the words on the wire gives the high word first again
    first, second = split32((int(words[0]) << 16) | int(words[1]), WordOrder(order) is CDAB)
    return struct.unpack(type_.struct_format, struct.pack(">HH", first, second))[0]


def float32_bits(value: float) -> int:
    """IEEE 754 single-precision bit pattern of ``value`` (rounded to nearest, as a C cast; overflow gives
    ±inf, NaN stays NaN)."""
    try:
        return struct.unpack(">I", struct.pack(">f", value))[0]
    except OverflowError:   # rounds beyond the largest float32
        return 0xFF800000 if value < 0 else 0x7F800000
