"""Register words: the data types a register can hold and the word order of 32-bit and 64-bit values.

Pure (standard library only, no pymodbus). Every 16-bit word travels big-endian (Modbus); a 32-bit value
(``uint32``, ``int32``, ``float32``) takes two consecutive registers, a ``float64`` four, in the
:class:`WordOrder` of the register (the device's ``word_order`` unless a configured map gives another)::

    value 0x12345678   ABCD: [0x1234, 0x5678]   (high word at the lower address, mbpoll -B)
                       CDAB: [0x5678, 0x1234]   (low word first, mbpoll's default)

A 64-bit value in ``CDAB`` is low word first too: its four words in reverse order (what pymodbus calls
``word_order="little"``). :func:`split32` is the one place that orders two words: the compiled image encoder
compiles this same function, and the Python codec and the clients call it, so they cannot disagree;
:func:`split_words` orders any number of words by the same rule.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from enum import StrEnum
from typing import Final

from valve_emulator.config.schema import WordOrder

__all__ = ["ABCD", "CDAB", "DataType", "WordOrder", "as_word_order", "float32_bits", "from_words", "split32",
           "split_words", "to_words"]

ABCD: Final = WordOrder.ABCD
CDAB: Final = WordOrder.CDAB


class DataType(StrEnum):
    """What a register (or a pair of registers) holds."""

    UINT16 = "uint16"
    INT16 = "int16"       # two's complement
    UINT32 = "uint32"     # two registers, in the word order
    INT32 = "int32"       # two registers, two's complement
    FLOAT32 = "float32"   # two registers, IEEE 754 single precision
    FLOAT64 = "float64"   # four registers, IEEE 754 double precision

    @property
    def is_float(self) -> bool:
        """Does the type hold an IEEE 754 float (the engineering value itself, no scale)?"""
        return self.raw_range is None

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
        """Smallest and largest integer the type holds (``None`` for the floats)."""
        return _LAYOUT[self][2]


_LAYOUT: Final = {
    DataType.UINT16: (1, ">H", (0, 0xFFFF)),
    DataType.INT16: (1, ">h", (-0x8000, 0x7FFF)),
    DataType.UINT32: (2, ">I", (0, 0xFFFFFFFF)),
    DataType.INT32: (2, ">i", (-0x80000000, 0x7FFFFFFF)),
    DataType.FLOAT32: (2, ">f", None),
    DataType.FLOAT64: (4, ">d", None),
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


def split_words(bits: int, width: int, cdab: bool) -> tuple[int, ...]:
    """The ``width`` register words of the ``16·width``-bit pattern ``bits``: high word first (ABCD), or
    low word first (``cdab``). ``split_words(b, 2, c) == split32(b, c)``."""
    words = tuple((bits >> (16 * k)) & 0xFFFF for k in range(width - 1, -1, -1))
    return words[::-1] if cdab else words


def to_words(value: float, type_: DataType | str, order: WordOrder | str = ABCD) -> list[int]:
    """Register words of ``value`` stored as ``type_`` (integers must fit the type; ``float32`` rounds).
    ``struct.error`` when an integer does not fit."""
    type_ = DataType(type_)
    packed = struct.pack(type_.struct_format, value)
    return list(split_words(int.from_bytes(packed, "big"), type_.width, WordOrder(order) is CDAB))


def from_words(words: Sequence[int], type_: DataType | str, order: WordOrder | str = ABCD) -> float:
    """The value that the first ``type_.width`` register ``words`` hold (inverse of :func:`to_words`)."""
    if type_ is DataType.UINT16 or type_ is DataType.INT16:   # one word (most writes): no order, no struct
        word = int(words[0]) & 0xFFFF
        return word - 0x10000 if type_ is DataType.INT16 and word >= 0x8000 else word
    type_ = DataType(type_)
    width = type_.width
    # the order is an involution: applying it to the words on the wire gives the high word first again
    ordered = split_words(sum(int(w) << (16 * (width - 1 - k)) for k, w in enumerate(words[:width])), width,
                          WordOrder(order) is CDAB)
    return struct.unpack(type_.struct_format, b"".join(w.to_bytes(2, "big") for w in ordered))[0]


def float32_bits(value: float) -> int:
    """IEEE 754 single-precision bit pattern of ``value`` (rounded to nearest, as a C cast; overflow gives
    ±inf, NaN stays NaN)."""
    try:
        return struct.unpack(">I", struct.pack(">f", value))[0]
    except OverflowError:   # rounds beyond the largest float32
        return 0xFF800000 if value < 0 else 0x7F800000
