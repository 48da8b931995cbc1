"""The compiled register encoder: every loop's registers, straight into the device's byte image, each tick.

Pure (numpy + numba, no pymodbus, no I/O). The Modbus adapter answers a read with a slice of one contiguous
``bytearray`` of big-endian words, so encoding is the only per-tick cost of the image. :func:`encode_image`
writes every loop's registers in one ``numba`` pass (scale, round half to even, clip, two's complement,
IEEE float32, word order, big-endian bytes): about 30 ns per loop on the benchmark machine, instead of one
numpy temporary per register column.

The kernel states no address, scale or range itself: it receives them from the register table
(:mod:`~valve_emulator.device.registers.table`) as plain ints and floats, computed once at import, which
numba compiles in as literals (see :func:`_compile`). The rules are those of
the plain-Python codec (:func:`~valve_emulator.device.registers.codec.encode_loop`); a test checks that
both give the same words.
"""

from __future__ import annotations

import sys
from typing import Any, Final, NamedTuple

import numba
import numpy as np

from valve_emulator.device.registers.scaling import Scaling
from valve_emulator.device.registers.table import MAP_VERSION, N_REGISTERS, Conversion, Fault, Status, register
from valve_emulator.device.registers.words import CDAB, DataType, float32_bits, split32
from valve_emulator.physics._arrays import kernel_array
from valve_emulator.physics.stiction import MV, STUCK

__all__ = ["ImageEncoder", "encode", "encode_image", "encode_words"]

_ROW_BYTES: Final = 2 * N_REGISTERS
#: The image is written through a native-order uint16 view: swap bytes on little-endian machines.
_SWAP = sys.byteorder == "little"
#: The word order of 32-bit values: the codec's own function, compiled.
_split32 = numba.njit(cache=True, inline="always")(split32)


class _Cell(NamedTuple):
    """What the kernel needs of one 16-bit register (32-bit ones use ``at`` only)."""

    at: int        # address inside the loop's block
    scale: float   # multiplier before rounding; 1 for the PV registers, whose scale is in the range factor
    lo: int        # raw range a reading is clipped to
    hi: int


def _cell(name: str) -> _Cell:
    reg = register(name)
    lo, hi = reg.read_range if reg.width == 1 else (0, 0)
    per_range = reg.conversion in (Conversion.PV_RANGE, Conversion.PV_SPAN)
    return _Cell(reg.address, 1.0 if per_range else float(reg.scale), int(lo), int(hi))


class _Map(NamedTuple):
    """The registers the kernel writes, by name (see the table)."""

    op_pct: _Cell
    op_ma: _Cell
    mv_pct: _Cell
    flow_pct: _Cell
    pv: _Cell
    sp: _Cell
    mode: _Cell
    kc: _Cell
    ti: _Cell
    td: _Cell
    S: _Cell
    J: _Cell
    status: _Cell
    map_version: _Cell
    tick: _Cell
    overruns: _Cell
    time: _Cell
    op_f32: _Cell
    mv_f32: _Cell
    pv_f32: _Cell
    sp_f32: _Cell
    load: _Cell
    noise: _Cell
    fault: _Cell


class _Constants(NamedTuple):
    """Numbers of the map that are not a register's cell: PV range factor, status and fault bits."""

    pv_full: float   # raw units per whole PV range: 100 · scale of the PV registers
    map_version: int
    stuck: int
    moving: int
    sat_low: int
    sat_high: int
    controller: int
    auto: int
    seized: int
    fault_seized: int


_MAP: Final = _Map(*(_cell(name) for name in _Map._fields))
#: The tick and overruns registers count modulo 2^32 (uint32), time is a float32: the same words on every loop.
assert [register(n).type for n in ("tick", "overruns", "time")] == [DataType.UINT32, DataType.UINT32,
                                                                     DataType.FLOAT32]
_PV_SCALES: Final = {register(n).scale for n in ("pv", "sp", "noise")}
assert len(_PV_SCALES) == 1, "pv, sp and noise share one range factor"
_CONSTANTS: Final = _Constants(
    100.0 * _PV_SCALES.pop(), MAP_VERSION, int(Status.STUCK), int(Status.MOVING),
    int(Status.SAT_LOW), int(Status.SAT_HIGH), int(Status.CONTROLLER), int(Status.AUTO), int(Status.SEIZED),
    int(Fault.SEIZED))


def _array(state: Any, name: str, n: int, dtype: np.dtype, optional: bool) -> np.ndarray:
    """``state.name`` as a contiguous array (n,) of ``dtype``; zeros for a missing optional array.

    A bank's arrays already have that form and are passed through untouched: at one loop the conversions
    would cost more than the compiled pass itself (the manual clock of the testing kit runs ticks back to back).
    A converted value is writable (:func:`~valve_emulator.physics._arrays.kernel_array`): numba compiles a
    kernel once per argument type, and a read-only array (what ``np.broadcast_to`` returns, and
    ``np.ascontiguousarray`` passes through) is a type of its own, so a state of lists or scalars compiled a
    second encoder (about 11 CPU s) beside the one for arrays.
    """
    value = getattr(state, name, None) if optional else getattr(state, name)
    if value is None:
        return np.zeros(n, dtype=dtype)
    if (type(value) is np.ndarray and value.dtype is dtype and value.shape == (n,) and value.flags.c_contiguous
            and value.flags.writeable):
        return value
    return kernel_array(np.broadcast_to(np.asarray(value, dtype=dtype), (n,)), dtype=dtype)


_F64: Final = np.dtype(np.float64)
_BOOL: Final = np.dtype(np.bool_)
#: The state's arrays the kernel reads, in its argument order after ``op``'s loop current: (name, dtype,
#: optional).
_INPUTS: Final = (("op", _F64, False), ("mv", _F64, False), ("flow", _F64, False), ("pv", _F64, False),
                  ("sp", _F64, False), ("kc", _F64, False), ("ti", _F64, False), ("td", _F64, False),
                  ("S", _F64, False), ("J", _F64, False), ("load", _F64, True), ("noise_std", _F64, True),
                  ("stuck", _BOOL, False), ("sat_low", _BOOL, False), ("sat_high", _BOOL, False),
                  ("has_controller", _BOOL, False), ("auto", _BOOL, False), ("frozen", _BOOL, True))


def _inputs(state: Any, n: int) -> list[np.ndarray]:
    """Every array of :data:`_INPUTS` as :func:`_array` gives it, in one pass: a bank's arrays are taken as they
    are after a few attribute checks (at one loop a function call per array would cost more than the kernel)."""
    shape = (n,)
    out = []
    for name, dtype, optional in _INPUTS:
        value = getattr(state, name, None)
        if not (type(value) is np.ndarray and value.dtype is dtype and value.shape == shape
                and value.flags.c_contiguous and value.flags.writeable):
            value = _array(state, name, n, dtype, optional)
        out.append(value)
    return out


def encode_image(state: Any, scaling: Scaling, image: bytearray | np.ndarray, offsets: np.ndarray, *,
                 tick: int, overruns: int, time: float) -> None:
    """Encode every loop's registers into ``image`` at byte ``offsets`` (pads and gaps are left alone).

    ``state`` is read as :func:`encode` describes (a ``LoopBank`` qualifies); ``image`` is a writable
    buffer of at least ``offsets.max() + 62`` bytes with even offsets.
    """
    ImageEncoder(scaling, image, offsets)(state, tick=tick, overruns=overruns, time=time)


class ImageEncoder:
    """:func:`encode_image` bound to one image and its offsets, checked once: the device's call at every tick,
    where the checks and conversions of the offsets would cost as much as the compiled pass at one loop."""

    def __init__(self, scaling: Scaling, image: bytearray | np.ndarray, offsets: np.ndarray) -> None:
        n = scaling.n
        offsets = np.ascontiguousarray(offsets, dtype=np.int64)
        if offsets.shape != (n,) or (n and (offsets.min() < 0 or offsets.max() + _ROW_BYTES > len(image)
                                            or np.any(offsets & 1))):
            raise ValueError(f"encode_image: need {n} even offsets inside an image of {len(image)} bytes")
        self.scaling = scaling
        self._words16 = np.frombuffer(image, dtype=np.uint16)  # native order: the kernel swaps bytes itself
        self._half = offsets // 2
        self._linear_ma = scaling.linear_ma

    def __call__(self, state: Any, *, tick: int, overruns: int, time: float) -> None:
        scaling = self.scaling
        # the codec's counters (modulo 2^32) and float32, as 32-bit patterns
        counters = (int(tick) & 0xFFFFFFFF, int(overruns) & 0xFFFFFFFF, float32_bits(float(time)),
                    scaling.word_order is CDAB, self._half, self._words16)
        live = getattr(state, "image_arrays", None)
        if live is not None:   # a loop bank: its own arrays, the derived values computed in the kernel
            op, *rest = live()
            ma = op if self._linear_ma else np.ascontiguousarray(scaling.op_to_ma(op), dtype=np.float64)
            _encode_bank_kernel(op, ma, self._linear_ma, *rest, scaling.pv_lo, scaling.pv_hi, *counters)
            return
        op, *rest = _inputs(state, scaling.n)
        _encode_kernel(op, np.ascontiguousarray(scaling.op_to_ma(op), dtype=np.float64), *rest,
                       scaling.pv_lo, scaling.pv_hi, *counters)


def encode_words(state: Any, scaling: Scaling, *, tick: int, overruns: int, time: float) -> np.ndarray:
    """The registers of every loop as an int64 array (n, N_REGISTERS) of 0..65535 (same kernel)."""
    n = scaling.n
    scratch = bytearray(_ROW_BYTES * n)
    encode_image(state, scaling, scratch, np.arange(n, dtype=np.int64) * _ROW_BYTES, tick=tick,
                 overruns=overruns, time=time)
    return np.frombuffer(scratch, dtype=">u2").reshape(n, N_REGISTERS).astype(np.int64)


def encode(state: Any, scaling: Scaling, *, tick: int, overruns: int, time: float,
           out: np.ndarray | None = None) -> np.ndarray:
    """Register words of every unit: array (n, N_REGISTERS) of int64 in 0..65535.

    Parameters
    ----------
    state : object with arrays (n,) ``op, mv, flow, pv, sp, kc, ti, td, S, J`` and bool arrays
        ``stuck, sat_low, sat_high, has_controller, auto`` (a ``LoopBank`` qualifies); the instructor's
        fault arrays ``load`` (% flow), ``noise_std`` (PV units) and ``frozen`` (bool) are optional and
        read as zero when the state has none.
    scaling : the per-unit :class:`~valve_emulator.device.registers.scaling.Scaling`.
    tick, overruns, time : device counters and simulated time (the same on every unit).
    out : optional preallocated array to fill.

    The device encodes straight into its byte image with the same compiled pass (:func:`encode_image`);
    this returns that pass's words.
    """
    w = encode_words(state, scaling, tick=tick, overruns=overruns, time=time)
    if out is None:
        return w
    out[...] = w
    return out


# --- the compiled pass ---------------------------------------------------------------------------------

@numba.njit(cache=True, inline="always")
def _word(x, cell):  # pragma: no cover - compiled
    """round(x·scale) half to even, clipped to the cell's range, as a 16-bit word; NaN reads as the bottom."""
    y = np.rint(x * cell.scale)
    if not y >= cell.lo:
        return cell.lo & 0xFFFF
    if y > cell.hi:
        return cell.hi & 0xFFFF
    return int(y) & 0xFFFF if cell.lo < 0 else int(y)   # two's complement for a signed range


@numba.njit(cache=True, inline="always")
def _put(img, at, value):  # pragma: no cover - compiled
    """Store one register word big-endian into the native-order uint16 view ``img``."""
    img[at] = ((value & 0xFF) << 8) | (value >> 8) if _SWAP else value


@numba.njit(cache=True, inline="always")
def _put32(img, at, bits, cdab):  # pragma: no cover - compiled
    """Store the 32-bit pattern ``bits`` (a float32's or a counter's) in two registers, in the word order."""
    first, second = _split32(np.int64(bits), cdab)   # unsigned and signed ints would mix into a float
    _put(img, at, first)
    _put(img, at + 1, second)


@numba.njit(cache=True, inline="always")
def _encode_row(m, k, img, b, op, ma, mv, flow, pv, sp, kc, ti, td, S, J, load, noise, stuck, sat_low, sat_high, c,
                auto, frozen, pv_lo, pv_hi, tick, overruns, time, cdab, f32):  # pragma: no cover - compiled
    """One loop's registers from its values, at word ``b`` of ``img``, by the cells ``m`` and constants ``k`` of
    the table (the kernels pass their frozen ones: inlined, they are literals); ``f32`` is a float32 scratch of 4.

    A module-level function, not one of :func:`_compile`'s closures: a kernel that calls a closure's compiled
    function cannot be cached on disk."""
    bits = f32.view(np.uint32)
    a = auto and c
    per_pv = k.pv_full / (pv_hi - pv_lo)
    _put(img, b + m.op_pct.at, _word(op, m.op_pct))
    _put(img, b + m.op_ma.at, _word(ma, m.op_ma))
    _put(img, b + m.mv_pct.at, _word(mv, m.mv_pct))
    _put(img, b + m.flow_pct.at, _word(flow, m.flow_pct))
    _put(img, b + m.pv.at, _word((pv - pv_lo) * per_pv, m.pv))
    # the controller's registers read 0 on a loop without one
    _put(img, b + m.sp.at, _word((sp - pv_lo) * per_pv, m.sp) if c else 0)
    _put(img, b + m.mode.at, 1 if a else 0)
    _put(img, b + m.kc.at, _word(kc, m.kc) if c else 0)
    _put(img, b + m.ti.at, _word(ti, m.ti) if (c and np.isfinite(ti) and ti > 0) else 0)   # 0: no integral
    _put(img, b + m.td.at, _word(td, m.td) if c else 0)
    _put(img, b + m.S.at, _word(S, m.S))
    _put(img, b + m.J.at, _word(J, m.J))
    _put(img, b + m.status.at, (k.stuck if stuck else k.moving) + (k.sat_low if sat_low else 0)
         + (k.sat_high if sat_high else 0) + (k.controller if c else 0) + (k.auto if a else 0)
         + (k.seized if frozen else 0))
    _put(img, b + m.map_version.at, k.map_version)
    _put32(img, b + m.tick.at, tick, cdab)
    _put32(img, b + m.overruns.at, overruns, cdab)
    _put32(img, b + m.time.at, time, cdab)
    f32[0], f32[1], f32[2], f32[3] = op, mv, pv, (sp if c else 0.0)
    _put32(img, b + m.op_f32.at, bits[0], cdab)
    _put32(img, b + m.mv_f32.at, bits[1], cdab)
    _put32(img, b + m.pv_f32.at, bits[2], cdab)
    _put32(img, b + m.sp_f32.at, bits[3], cdab)
    _put(img, b + m.load.at, _word(load, m.load))
    # a width w in PV units reads like the PV lo + w (the codec's rule, kept float for float)
    _put(img, b + m.noise.at, _word(((pv_lo + noise) - pv_lo) * per_pv, m.noise))
    _put(img, b + m.fault.at, k.fault_seized if frozen else 0)


@numba.njit(cache=True, inline="always")
def _encode_bank_rows(m, k, img, word0, op, ma, linear_ma, valve, flow, pv, sp, kc, ti_inv, td, S, J, load, noise,
                      auto, ctl, frozen, pv_lo, pv_hi, tick, overruns, time, cdab):  # pragma: no cover - compiled
    """Every loop's registers (:func:`_encode_row`) from a loop bank's own arrays: ``mv`` and ``stuck`` from the
    valve state, ``ti`` from ``1/ti``, the saturation flags from OP and, with ``linear_ma`` (no custom mA table),
    the loop current ``4 + 0.16·OP`` -- the bank's properties' and the scaling's numbers, computed here. The image
    encoder's bank kernel and the device's one-call tick (:mod:`valve_emulator.device.tick_kernel`) both call it."""
    f32 = np.empty(4, np.float32)
    for i in range(op.shape[0]):
        o = op[i]
        inv = ti_inv[i]
        _encode_row(m, k, img, word0[i], o, 4.0 + 0.16 * o if linear_ma else ma[i], valve[i, MV], flow[i], pv[i],
                    sp[i], kc[i], np.inf if inv == 0.0 else 1.0 / inv, td[i], S[i], J[i], load[i], noise[i],
                    valve[i, STUCK] == 1.0, o <= 0.0, o >= 100.0, ctl[i], auto[i], frozen[i], pv_lo[i],
                    pv_hi[i], tick, overruns, time, cdab, f32)


def _compile(m: _Map, k: _Constants):
    """The kernel for the table's cells ``m`` and constants ``k``, which numba freezes as literals.

    They reach the kernel as closure variables: numba keys its on-disk cache on their values (as well as
    on this file), so a changed table compiles a new kernel instead of loading a stale one.
    """

    @numba.njit(cache=True)
    def encode_kernel(op, ma, mv, flow, pv, sp, kc, ti, td, S, J, load, noise, stuck, sat_low, sat_high, ctl,
                      auto, frozen, pv_lo, pv_hi, tick, overruns, time, cdab, word0,
                      img):  # pragma: no cover - compiled
        f32 = np.empty(4, np.float32)
        for i in range(op.shape[0]):
            _encode_row(m, k, img, word0[i], op[i], ma[i], mv[i], flow[i], pv[i], sp[i], kc[i], ti[i], td[i], S[i],
                        J[i], load[i], noise[i], stuck[i], sat_low[i], sat_high[i], ctl[i], auto[i], frozen[i],
                        pv_lo[i], pv_hi[i], tick, overruns, time, cdab, f32)

    @numba.njit(cache=True)
    def encode_bank_kernel(op, ma, linear_ma, valve, flow, pv, sp, kc, ti_inv, td, S, J, load, noise, auto, ctl,
                           frozen, pv_lo, pv_hi, tick, overruns, time, cdab, word0,
                           img):  # pragma: no cover - compiled
        """:func:`encode_kernel` from a loop bank's own arrays (``LoopBank.image_arrays``,
        :func:`_encode_bank_rows`)."""
        _encode_bank_rows(m, k, img, word0, op, ma, linear_ma, valve, flow, pv, sp, kc, ti_inv, td, S, J, load, noise,
                          auto, ctl, frozen, pv_lo, pv_hi, tick, overruns, time, cdab)

    return encode_kernel, encode_bank_kernel


_encode_kernel, _encode_bank_kernel = _compile(_MAP, _CONSTANTS)
