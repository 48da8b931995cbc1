"""The register image: where each loop's registers live, and one compiled pass that encodes all of them.

Pure (numpy + numba, no pymodbus, no I/O). The Modbus adapter answers a read with a slice of one
contiguous ``bytearray`` of big-endian words, so encoding is the only per-tick cost of the image.

Layout (see also :mod:`~valve_emulator.device.registers`)
----------------------------------------------------------
Every loop has an address ``(unit, block)``. Block ``k`` of a unit starts at register address
``k·BLOCK_STRIDE`` (``BLOCK_STRIDE = 32``): its 31 registers (:data:`N_REGISTERS`) occupy
``32k .. 32k + 30`` and address ``32k + 31`` is a *pad* that reads 0. The blocks of a unit are
``0 .. B−1`` without gaps, so a unit's holding-register space is ``0 .. 32(B−1) + 30`` and one read of
125 registers polls about four loops. With one block per unit (``B = 1``, the classic layout) a unit's
space is exactly the register map, 0..30.

In the image each unit owns one region of ``32(B−1) + 31`` words, in the order the units first appear;
a loop's words start at byte ``region_start(unit) + 64·block``. With one block per unit the image is the
loops' 31-word rows back to back, in loop order.

Encoding
--------
:func:`encode_image` writes every loop's registers straight into the image in one ``numba`` pass
(scale, round half to even, clip, two's complement, IEEE float32, word order, big-endian bytes): about
30 ns per loop on the benchmark machine, instead of one numpy temporary per register column. The rules are those
documented in :mod:`~valve_emulator.device.registers`; :func:`~valve_emulator.device.registers.encode`
(the words as an array) is this same kernel writing into a scratch image.
"""

from __future__ import annotations

import sys
from typing import Any, Final, Sequence

import numba
import numpy as np

from valve_emulator.device.registers import (
    BLOCK_STRIDE,
    CDAB,
    MAP_VERSION,
    MAX_BLOCKS,
    N_REGISTERS,
    Fault,
    RegisterAddressError,
    Scaling,
    Status,
    address_of,
)

__all__ = ["ImageLayout", "encode_image", "encode_words"]

_BLOCK_BYTES: Final = 2 * BLOCK_STRIDE
_ROW_BYTES: Final = 2 * N_REGISTERS
# Register addresses the kernel writes (the map in registers.py owns them; numba sees plain ints).
(_OP_PCT, _OP_MA, _MV_PCT, _FLOW_PCT, _PV, _SP, _MODE, _KC, _TI, _TD, _S, _J, _STATUS, _MAP_VERSION, _TICK,
 _OP_F32, _MV_F32, _PV_F32, _SP_F32, _LOAD, _NOISE, _FAULT) = (address_of(name) for name in (
    "op_pct", "op_ma", "mv_pct", "flow_pct", "pv", "sp", "mode", "kc", "ti", "td", "S", "J", "status",
    "map_version", "tick", "op_f32", "mv_f32", "pv_f32", "sp_f32", "load", "noise", "fault"))
_STUCK, _MOVING, _SAT_LOW, _SAT_HIGH, _CONTROLLER, _AUTO, _SEIZED = (int(b) for b in (
    Status.STUCK, Status.MOVING, Status.SAT_LOW, Status.SAT_HIGH, Status.CONTROLLER, Status.AUTO, Status.SEIZED))
_FAULT_SEIZED = int(Fault.SEIZED)
# The kernel writes the 32-bit values as consecutive words from these starts.
assert (_MV_F32, _PV_F32, _SP_F32) == (_OP_F32 + 2, _OP_F32 + 4, _OP_F32 + 6)
assert (address_of("overruns"), address_of("time")) == (_TICK + 2, _TICK + 4)
#: The image is written through a native-order uint16 view: swap bytes on little-endian machines.
_SWAP = sys.byteorder == "little"


class ImageLayout:
    """Where each of ``n`` loops lives: unit ids and blocks -> byte offsets in the image.

    Parameters
    ----------
    units : the unit id (0..255) of each loop, in bank order.
    blocks : the block of each loop inside its unit (default all 0: one loop per unit). The pairs
        ``(unit, block)`` must be unique and each unit's blocks must be ``0 .. B−1`` without gaps.

    Attributes
    ----------
    offsets : int64 array (n,), byte offset of each loop's first register in the image.
    size : bytes of the whole image.
    regions : ``unit -> (start byte, number of blocks)``.
    loops_of : ``unit -> tuple of loop indices, by block``.
    """

    def __init__(self, units: Sequence[int], blocks: Sequence[int] | None = None) -> None:
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
        self.units, self.blocks = units, blocks
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
            start += _BLOCK_BYTES * (count - 1) + _ROW_BYTES
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

        A write stays inside one loop's block: one that reaches a pad or the next block raises
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
                f"k = 0..{len(loops) - 1})")
        return loops[block], offset


def _common_words(tick: int, overruns: int, time: float, word_order: str) -> np.ndarray:
    """The words shared by every loop: tick, overruns (uint32) and time (float32), in register order."""
    raw = np.concatenate([np.array([int(tick) & 0xFFFFFFFF, int(overruns) & 0xFFFFFFFF], dtype=">u4").view(">u2"),
                          np.array([time], dtype=">f4").view(">u2")]).astype(np.int64).reshape(3, 2)
    return np.ascontiguousarray(raw[:, ::-1] if word_order == CDAB else raw).reshape(-1)


def _floats(state: Any, name: str, n: int, optional: bool = False) -> np.ndarray:
    value = getattr(state, name, None) if optional else getattr(state, name)
    if value is None:
        return np.zeros(n)
    return np.ascontiguousarray(np.broadcast_to(np.asarray(value, dtype=np.float64), (n,)))


def _bools(state: Any, name: str, n: int, optional: bool = False) -> np.ndarray:
    value = getattr(state, name, None) if optional else getattr(state, name)
    if value is None:
        return np.zeros(n, dtype=np.bool_)
    return np.ascontiguousarray(np.broadcast_to(np.asarray(value, dtype=np.bool_), (n,)))


def encode_image(state: Any, scaling: Scaling, image: bytearray | np.ndarray, offsets: np.ndarray, *,
                 tick: int, overruns: int, time: float) -> None:
    """Encode every loop's registers into ``image`` at byte ``offsets`` (pads and gaps are left alone).

    ``state`` is read as :func:`~valve_emulator.device.registers.encode` describes (a ``LoopBank``
    qualifies); ``image`` is a writable buffer of at least ``offsets.max() + 62`` bytes with even offsets.
    """
    n = scaling.n
    offsets = np.ascontiguousarray(offsets, dtype=np.int64)
    if offsets.shape != (n,) or (n and (offsets.min() < 0 or offsets.max() + _ROW_BYTES > len(image)
                                        or np.any(offsets & 1))):
        raise ValueError(f"encode_image: need {n} even offsets inside an image of {len(image)} bytes")
    op = _floats(state, "op", n)
    words16 = np.frombuffer(image, dtype=np.uint16)  # native order: the kernel swaps bytes itself
    _encode_kernel(op, np.ascontiguousarray(scaling.op_to_ma(op), dtype=np.float64), _floats(state, "mv", n),
                   _floats(state, "flow", n), _floats(state, "pv", n), _floats(state, "sp", n),
                   _floats(state, "kc", n), _floats(state, "ti", n), _floats(state, "td", n),
                   _floats(state, "S", n), _floats(state, "J", n), _floats(state, "load", n, True),
                   _floats(state, "noise_std", n, True), _bools(state, "stuck", n),
                   _bools(state, "sat_low", n), _bools(state, "sat_high", n), _bools(state, "has_controller", n),
                   _bools(state, "auto", n), _bools(state, "frozen", n, True), scaling.pv_lo, scaling.pv_hi,
                   _common_words(tick, overruns, time, scaling.word_order), scaling.word_order == CDAB,
                   offsets // 2, words16)


def encode_words(state: Any, scaling: Scaling, *, tick: int, overruns: int, time: float) -> np.ndarray:
    """The registers of every loop as an int64 array (n, N_REGISTERS) of 0..65535 (same kernel)."""
    n = scaling.n
    scratch = bytearray(_ROW_BYTES * n)
    encode_image(state, scaling, scratch, np.arange(n, dtype=np.int64) * _ROW_BYTES, tick=tick,
                 overruns=overruns, time=time)
    return np.frombuffer(scratch, dtype=">u2").reshape(n, N_REGISTERS).astype(np.int64)


# --- the compiled pass ---------------------------------------------------------------------------------

@numba.njit(cache=True, inline="always")
def _u16(x, scale, lo, hi):  # pragma: no cover - compiled
    """round(x·scale) half to even, clipped to lo..hi; NaN reads as lo."""
    y = np.rint(x * scale)
    if not y >= lo:
        return lo
    if y > hi:
        return hi
    return int(y)


@numba.njit(cache=True, inline="always")
def _i16(x):  # pragma: no cover - compiled
    return _u16(x, 1.0, -32768, 32767) & 0xFFFF


@numba.njit(cache=True, inline="always")
def _put(img, at, value):  # pragma: no cover - compiled
    """Store one register word big-endian into the native-order uint16 view ``img``."""
    img[at] = ((value & 0xFF) << 8) | (value >> 8) if _SWAP else value


@numba.njit(cache=True)
def _encode_kernel(op, ma, mv, flow, pv, sp, kc, ti, td, S, J, load, noise, stuck, sat_low, sat_high, ctl,
                   auto, frozen, pv_lo, pv_hi, common, cdab, word0, img):  # pragma: no cover - compiled
    f32 = np.empty(4, np.float32)
    bits = f32.view(np.uint32)
    for i in range(op.shape[0]):
        b = word0[i]
        c = ctl[i]
        a = auto[i] and c
        k = 10000.0 / (pv_hi[i] - pv_lo[i])
        _put(img, b + _OP_PCT, _u16(op[i], 100.0, 0, 10000))
        _put(img, b + _OP_MA, _u16(ma[i], 1000.0, 0, 65535))
        _put(img, b + _MV_PCT, _u16(mv[i], 100.0, 0, 10000))
        _put(img, b + _FLOW_PCT, _u16(flow[i], 100.0, 0, 10000))
        _put(img, b + _PV, _i16((pv[i] - pv_lo[i]) * k))
        _put(img, b + _SP, _i16((sp[i] - pv_lo[i]) * k) if c else 0)
        _put(img, b + _MODE, 1 if a else 0)
        _put(img, b + _KC, _u16(kc[i], 1000.0, 0, 65535) if c else 0)
        t = ti[i]
        _put(img, b + _TI, _u16(t, 10.0, 1, 65535) if (c and np.isfinite(t) and t > 0) else 0)
        _put(img, b + _TD, _u16(td[i], 10.0, 0, 65535) if c else 0)
        _put(img, b + _S, _u16(S[i], 100.0, 0, 65535))
        _put(img, b + _J, _u16(J[i], 100.0, 0, 65535))
        _put(img, b + _STATUS, (_STUCK if stuck[i] else _MOVING) + (_SAT_LOW if sat_low[i] else 0)
             + (_SAT_HIGH if sat_high[i] else 0) + (_CONTROLLER if c else 0) + (_AUTO if a else 0)
             + (_SEIZED if frozen[i] else 0))
        _put(img, b + _MAP_VERSION, MAP_VERSION)
        for r in range(6):
            _put(img, b + _TICK + r, common[r])
        f32[0], f32[1], f32[2], f32[3] = op[i], mv[i], pv[i], (sp[i] if c else 0.0)
        for j in range(4):
            u = np.int64(bits[j])   # unsigned and signed ints would mix into a float in numba
            hi, lo = u >> 16, u & 0xFFFF
            _put(img, b + _OP_F32 + 2 * j, lo if cdab else hi)
            _put(img, b + _OP_F32 + 2 * j + 1, hi if cdab else lo)
        _put(img, b + _LOAD, _i16(load[i] * 100.0))
        _put(img, b + _NOISE, _u16(((pv_lo[i] + noise[i]) - pv_lo[i]) * k, 1.0, 0, 10000))
        _put(img, b + _FAULT, _FAULT_SEIZED if frozen[i] else 0)
