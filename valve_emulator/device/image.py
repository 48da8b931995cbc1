"""The register image: where each loop's registers live among the unit ids and their blocks.

Pure (numpy, no pymodbus, no I/O). The Modbus adapter answers a read with a slice of one contiguous
``bytearray`` of big-endian words; :func:`~valve_emulator.device.registers.encode_image` fills it at the
byte offsets computed here.

Layout (see also :mod:`~valve_emulator.device.registers`)
----------------------------------------------------------
Every loop has an address ``(unit, block)``. Block ``k`` of a unit starts at register address
``k·BLOCK_STRIDE`` (``BLOCK_STRIDE = 32``): its 32 registers (:data:`N_REGISTERS`) occupy
``32k .. 32k + 31``. The blocks of a unit are ``0 .. B−1`` without gaps, so a unit's holding-register space
is ``0 .. 32(B−1) + 31`` and one read of 125 registers polls about four loops. With one block per unit
(``B = 1``, the classic layout) a unit's space is exactly the register map, 0..31.

In the image each unit owns one region of ``32(B−1) + 31`` words, in the order the units first appear;
a loop's words start at byte ``region_start(unit) + 64·block``. With one block per unit the image is the
loops' 31-word rows back to back, in loop order.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import numpy as np

from valve_emulator.device.registers import BLOCK_STRIDE, MAX_BLOCKS, N_REGISTERS, RegisterAddressError

__all__ = ["ImageLayout"]

_BLOCK_BYTES: Final = 2 * BLOCK_STRIDE


class ImageLayout:
    """Where each of ``n`` loops lives: unit ids and blocks -> byte offsets in the image.

    Parameters
    ----------
    units : the unit id (0..255) of each loop, in bank order.
    blocks : the block of each loop inside its unit (default all 0: one loop per unit). The pairs
        ``(unit, block)`` must be unique and each unit's blocks must be ``0 .. B−1`` without gaps.
    row_words : words of one loop's row: :data:`N_REGISTERS` for the standard map, the served row of a
        configured register map otherwise (one loop per unit).

    Attributes
    ----------
    offsets : int64 array (n,), byte offset of each loop's first register in the image.
    size : bytes of the whole image.
    regions : ``unit -> (start byte, number of blocks)``.
    loops_of : ``unit -> tuple of loop indices, by block``.
    """

    def __init__(self, units: Sequence[int], blocks: Sequence[int] | None = None, *,
                 row_words: int = N_REGISTERS) -> None:
        units = tuple(int(u) for u in units)
        blocks = (0,) * len(units) if blocks is None else tuple(int(b) for b in blocks)
        if len(blocks) != len(units):
            raise ValueError(f"ImageLayout: {len(units)} units but {len(blocks)} blocks")
        if not all(0 <= u <= 255 for u in units):
            raise ValueError(f"ImageLayout: units must be ids in 0..255, got {sorted(set(units))[:10]}")
        if not all(0 <= b < MAX_BLOCKS for b in blocks):
            raise ValueError(f"ImageLayout: blocks must be in 0..{MAX_BLOCKS - 1}")
        by_unit: dict[int, dict[int, int]] = {}
        for i, (u, b) in enumerate(zip(units, blocks)):
            slots = by_unit.setdefault(u, {})
            if b in slots:
                raise ValueError(f"ImageLayout: units must be unique ids (unit {u} block {b} is given to loops "
                                 f"{slots[b]} and {i})")
            slots[b] = i
        if row_words != N_REGISTERS and any(blocks):
            raise ValueError("ImageLayout: only the standard map's rows fit blocks of several loops per unit")
        self.units, self.blocks, self.row_words = units, blocks, row_words
        self.regions: dict[int, tuple[int, int]] = {}
        self.loops_of: dict[int, tuple[int, ...]] = {}
        start = 0
        for u, slots in by_unit.items():
            count = len(slots)
            if max(slots) != count - 1:
                raise ValueError(f"ImageLayout: unit {u} has blocks {sorted(slots)[:10]}; the blocks of a unit "
                                 f"must be 0..B-1 without gaps")
            self.regions[u] = (start, count)
            self.loops_of[u] = tuple(slots[b] for b in range(count))
            start += _BLOCK_BYTES * (count - 1) + 2 * row_words
        self.size = start
        self.offsets = np.array([self.regions[u][0] + _BLOCK_BYTES * b for u, b in zip(units, blocks)],
                                dtype=np.int64)

    @property
    def n(self) -> int:
        return len(self.units)

    @property
    def blocked(self) -> bool:
        """Does any unit carry more than one loop?"""
        return any(count > 1 for _, count in self.regions.values())

    def locate_write(self, unit: int, address: int, count: int) -> tuple[int, int]:
        """``(loop index, address inside its block)`` of a write of ``count`` registers at ``address``.

        A write stays inside one loop's block: one that reaches the next block raises
        :class:`~valve_emulator.device.registers.RegisterAddressError`. With one block per unit the
        address is passed on unchanged (the register map then checks it).
        """
        loops = self.loops_of[unit]
        if len(loops) == 1:
            return loops[0], address
        block, offset = divmod(address, BLOCK_STRIDE)
        if address < 0 or block >= len(loops) or offset + count > N_REGISTERS:
            raise RegisterAddressError(
                f"holding registers {address}..{address + count - 1} are not inside one loop's block "
                f"(block k holds addresses {BLOCK_STRIDE}k..{BLOCK_STRIDE}k+{N_REGISTERS - 1}, "
                f"k = 0..{len(loops) - 1})", address=address, count=count)
        return loops[block], offset
