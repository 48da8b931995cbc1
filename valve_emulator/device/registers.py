"""The Modbus register map: every address, type and scaling of the emulated device, in one table.

Pure code (numpy only, no pymodbus, no I/O). Addresses are zero-based PDU addresses (mbpoll ``-0``). Every
unit id carries the same layout; only the per-loop scalings (PV range, mA table) differ. :data:`REGISTERS`
is the single source of truth; :func:`registers_table` and :func:`format_registers` render it as
Markdown, CSV or JSON, and the table below is that rendering (a test keeps them equal).

Holding registers (function codes 3, 6, 16, 23)::

    | name        | table   | address | type    | scale | units               | access        |
    |-------------|---------|---------|---------|-------|---------------------|---------------|
    | op_pct      | holding | 0       | uint16  | 100   | % travel            | RW            |
    | op_ma       | holding | 1       | uint16  | 1000  | mA                  | RW            |
    | mv_pct      | holding | 2       | uint16  | 100   | % travel            | R             |
    | flow_pct    | holding | 3       | uint16  | 100   | % flow              | R             |
    | pv          | holding | 4       | int16   | 100   | % of pv_range       | R             |
    | sp          | holding | 5       | int16   | 100   | % of pv_range       | RW-controller |
    | mode        | holding | 6       | uint16  | 1     | 0 manual, 1 auto    | RW-controller |
    | kc          | holding | 7       | uint16  | 1000  | % per PV unit       | RW-controller |
    | ti          | holding | 8       | uint16  | 10    | s (0 = no integral) | RW-controller |
    | td          | holding | 9       | uint16  | 10    | s                   | RW-controller |
    | S           | holding | 10      | uint16  | 100   | % travel            | RW-instructor |
    | J           | holding | 11      | uint16  | 100   | % travel            | RW-instructor |
    | status      | holding | 12      | uint16  | 1     | bits                | R             |
    | map_version | holding | 13      | uint16  | 1     |                     | R             |
    | tick        | holding | 14      | uint32  | 1     | ticks               | R             |
    | overruns    | holding | 16      | uint32  | 1     | ticks               | R             |
    | time        | holding | 18      | float32 | 1     | s                   | R             |
    | op_f32      | holding | 20      | float32 | 1     | % travel            | R             |
    | mv_f32      | holding | 22      | float32 | 1     | % travel            | R             |
    | pv_f32      | holding | 24      | float32 | 1     | PV units            | R             |
    | sp_f32      | holding | 26      | float32 | 1     | PV units            | R             |
    | load        | holding | 28      | int16   | 100   | % flow              | RW-instructor |
    | noise       | holding | 29      | uint16  | 100   | % of pv_range       | RW-instructor |
    | fault       | holding | 30      | uint16  | 1     | bits                | RW-instructor |

The rows a controller cannot write -- read-only (``R``) and instructor (``RW-instructor``) -- also appear
as input registers (function code 4) at the same addresses, so a read-only client sees injected faults
too; the input table has holes where the holding table has registers a controller writes (``op_pct`` ..
``td``), and reading a hole is an illegal address, as is reading past address 30.

Encoding (``raw = physical × scale``, rounded to the nearest integer, clipped to the type's range):

- ``op_pct``/``mv_pct``/``flow_pct``: % × 100, 0..10000. ``op_ma``: the OP as loop current through the
  loop's ``valve.ma_table`` (default linear 4–20 mA), mA × 1000. Writing either one sets OP; both read
  back consistently. The writable ``op_ma`` range is the current that maps onto 0..100 % travel
  (4000..20000 for the default table).
- ``pv``/``sp``: int16, ``10000·(x − lo)/(hi − lo)`` over the loop's ``plant.pv_range`` = (lo, hi), so
  0..10000 spans the range and values outside it stay readable down to −327.68 % / up to 327.67 %.
  ``sp`` writes must lie in 0..10000. The float32 copies carry engineering units.
- ``ti`` = 0 means no integral action (P only; the bank gets ``ti = inf``). ``kc`` must be ≥ 0.001.
- ``status`` bits: see :class:`Status`.
- Instructor faults (issue 5): ``load`` adds a load disturbance of ``load/100`` % flow to the plant input
  (int16, -10000..10000); ``noise`` sets the standard deviation of the PV measurement noise in % of the
  loop's ``pv_range`` × 100 (0..10000; % of span, like ``pv``, so one number means the same on every
  loop); ``fault`` bit 0 (:class:`Fault`) seizes the valve: it holds its position whatever OP does until
  the bit is cleared (other bits are refused). ``status`` bit ``SEIZED`` mirrors it.
- ``time`` (simulated s) is a float32: 0.1 s resolution holds for about six days of simulated time; for
  exact time use ``tick × dt``. ``tick`` and ``overruns`` wrap at 2³².
- 32-bit values (``uint32`` and ``float32``) use the configured word order: ``ABCD`` puts the high word
  at the lower address (mbpoll ``-B``), ``CDAB`` the low word first (mbpoll's default).

Access:

- ``R``: read only. ``RW``: writable; on a loop with an internal controller OP is writable only while the
  controller is in manual (it then sets the manual OP) and only within the controller's ``op_limits``. ``RW-controller``: writable only on loops with an
  internal controller, reads 0 on the others. ``RW-instructor``: writable only when the server allows
  instructor writes for the requesting client.

Errors are :class:`RegisterError` (a ``ValueError``) subclasses that name the register; the Modbus
adapter alone translates them into exception codes. A rejected multi-register write changes nothing.

Many loops per unit id (blocks)
-------------------------------
A plant-size fleet (``fleet.loops_per_unit`` > 1, see ``docs/config.md``) puts several loops behind one
unit id, each in its own *block* of :data:`BLOCK_STRIDE` = 32 registers: loop ``k`` of the unit answers
at addresses ``32k .. 32k + 30`` with exactly the map above shifted by ``32k``, so loop 3's ``pv`` is
holding register ``3·32 + 4 = 100``. Address ``32k + 31`` is a pad. A unit of ``B`` blocks spans
``0 .. 32(B−1) + 30``: at most :data:`MAX_BLOCKS` = 2048 blocks (the 16-bit address space), so one port
serves up to 247 × 2048 loops.

- Holding reads (FC3 and the read half of FC23) may span blocks: one read of 125 registers polls about
  four loops, which is how a SCADA driver polls many loops cheaply. Pads read 0.
- Input reads (FC4) stay inside one block (the input table has holes in every block anyway).
- Writes stay inside one block; a write that reaches a pad or the next block is an illegal address.

With one block per unit (the default) nothing changes: the unit's map is 0..30 and address 31 is outside it.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from enum import IntFlag
from typing import Any, Final, Sequence

import numpy as np

from valve_emulator.device.scaling import ABCD, CDAB, Scaling

__all__ = [
    "ABCD",
    "BLOCK_STRIDE",
    "DEFAULT_PORT",
    "CDAB",
    "MAP_VERSION",
    "MAX_BLOCKS",
    "N_REGISTERS",
    "REGISTERS",
    "INPUT_REGISTERS",
    "ACCESS_VALUES",
    "Register",
    "Status",
    "Fault",
    "Scaling",
    "RegisterError",
    "RegisterAddressError",
    "RegisterAccessError",
    "RegisterValueError",
    "address_of",
    "check_read",
    "encode",
    "patch",
    "decode_write",
    "registers_table",
    "format_registers",
]

#: TCP port `valve-emulator serve` listens on by default (clients default to it too).
DEFAULT_PORT: Final = 5020
MAP_VERSION: Final = 2   # 2: load, noise, fault registers; instructor rows mirrored as input

R: Final = "R"
RW: Final = "RW"
RW_CONTROLLER: Final = "RW-controller"
RW_INSTRUCTOR: Final = "RW-instructor"
ACCESS_VALUES: Final = (R, RW, RW_CONTROLLER, RW_INSTRUCTOR)

_WIDTH: Final = {"uint16": 1, "int16": 1, "uint32": 2, "float32": 2}


class Status(IntFlag):
    """Bits of the ``status`` register."""

    STUCK = 1           # valve at rest (stiction holds it)
    MOVING = 2          # valve moving (the complement of STUCK)
    SAT_LOW = 4         # OP clipped at 0 %
    SAT_HIGH = 8        # OP clipped at 100 %
    CONTROLLER = 16     # the loop has an internal PI(D) controller
    AUTO = 32           # that controller is in auto
    SEIZED = 64         # instructor fault: the valve is seized (``fault`` bit 0), it does not move at all


class Fault(IntFlag):
    """Bits of the instructor's ``fault`` register (bits not listed here are refused)."""

    SEIZED = 1          # the valve sticks completely, whatever OP does


@dataclass(frozen=True, slots=True)
class Register:
    """One row of the map. ``quantity`` names the model value it carries; ``lo..hi`` is the raw write range."""

    name: str
    address: int
    type: str
    scale: int
    units: str
    access: str
    quantity: str
    lo: int = 0
    hi: int = 0

    @property
    def width(self) -> int:
        return _WIDTH[self.type]


REGISTERS: Final[tuple[Register, ...]] = (
    Register("op_pct", 0, "uint16", 100, "% travel", RW, "op", 0, 10000),   # write range per loop:
    Register("op_ma", 1, "uint16", 1000, "mA", RW, "op", 4000, 20000),     # see Scaling.op_limits
    Register("mv_pct", 2, "uint16", 100, "% travel", R, "mv"),
    Register("flow_pct", 3, "uint16", 100, "% flow", R, "flow"),
    Register("pv", 4, "int16", 100, "% of pv_range", R, "pv"),
    Register("sp", 5, "int16", 100, "% of pv_range", RW_CONTROLLER, "sp", 0, 10000),
    Register("mode", 6, "uint16", 1, "0 manual, 1 auto", RW_CONTROLLER, "auto", 0, 1),
    Register("kc", 7, "uint16", 1000, "% per PV unit", RW_CONTROLLER, "kc", 1, 65535),
    Register("ti", 8, "uint16", 10, "s (0 = no integral)", RW_CONTROLLER, "ti", 0, 65535),
    Register("td", 9, "uint16", 10, "s", RW_CONTROLLER, "td", 0, 65535),
    Register("S", 10, "uint16", 100, "% travel", RW_INSTRUCTOR, "S", 0, 10000),
    Register("J", 11, "uint16", 100, "% travel", RW_INSTRUCTOR, "J", 0, 10000),
    Register("status", 12, "uint16", 1, "bits", R, "status"),
    Register("map_version", 13, "uint16", 1, "", R, "map_version"),
    Register("tick", 14, "uint32", 1, "ticks", R, "tick"),
    Register("overruns", 16, "uint32", 1, "ticks", R, "overruns"),
    Register("time", 18, "float32", 1, "s", R, "time"),
    Register("op_f32", 20, "float32", 1, "% travel", R, "op"),
    Register("mv_f32", 22, "float32", 1, "% travel", R, "mv"),
    Register("pv_f32", 24, "float32", 1, "PV units", R, "pv"),
    Register("sp_f32", 26, "float32", 1, "PV units", R, "sp"),
    # instructor fault injection (issue 5): written by the training-scenario player, read by everyone
    Register("load", 28, "int16", 100, "% flow", RW_INSTRUCTOR, "load", -10000, 10000),
    Register("noise", 29, "uint16", 100, "% of pv_range", RW_INSTRUCTOR, "noise", 0, 10000),
    Register("fault", 30, "uint16", 1, "bits", RW_INSTRUCTOR, "fault", 0, 1),
)
# Input registers mirror what a controller cannot write: the read-only rows and the instructor rows.
INPUT_REGISTERS: Final = tuple(r for r in REGISTERS if r.access in (R, RW_INSTRUCTOR))
N_REGISTERS: Final = REGISTERS[-1].address + REGISTERS[-1].width
#: Registers between the starts of consecutive loops of one unit (blocks layout); one pad after the map.
BLOCK_STRIDE: Final = 32
#: Most loops (blocks) one unit id can carry: the 16-bit register address space / BLOCK_STRIDE.
MAX_BLOCKS: Final = 65536 // BLOCK_STRIDE
assert N_REGISTERS < BLOCK_STRIDE  # a block must hold the whole map

_BY_NAME: Final = {r.name: r for r in REGISTERS}
_HOLDING_AT: Final = {r.address + w: r for r in REGISTERS for w in range(r.width)}
# _INPUT_RUN_END[a]: first address after the run of mapped input registers starting at a (a if unmapped);
# lets the adapter validate any FC4 read with one comparison.
_INPUT_MAPPED: Final = [any(r.address <= a < r.address + r.width for r in INPUT_REGISTERS)
                        for a in range(N_REGISTERS)] + [False]
_INPUT_RUN_END: Final = list(range(N_REGISTERS + 1))
for _a in range(N_REGISTERS - 1, -1, -1):
    if _INPUT_MAPPED[_a]:
        _INPUT_RUN_END[_a] = _INPUT_RUN_END[_a + 1] if _INPUT_MAPPED[_a + 1] else _a + 1
_A: Final = {r.name: r.address for r in REGISTERS}


class RegisterError(ValueError):
    """A request the register map refuses; the message names the register."""


class RegisterAddressError(RegisterError):
    """The addresses are not in the map (or not in the requested table)."""


class RegisterAccessError(RegisterError):
    """The register exists but may not be written (read-only, no controller, no permission, auto mode)."""


class RegisterValueError(RegisterError):
    """The raw value is outside the register's range."""


def address_of(name: str) -> int:
    """Zero-based address of register ``name`` (``KeyError`` naming it when unknown)."""
    try:
        return _BY_NAME[name].address
    except KeyError:
        raise KeyError(f"no register named {name!r}; known: {', '.join(_BY_NAME)}") from None


def check_read(table: str, address: int, count: int, *, blocks: int = 1) -> None:
    """Raise :class:`RegisterAddressError` unless ``count`` registers from ``address`` are all mapped.

    ``blocks`` is the number of loops behind the unit (see *Many loops per unit id*): a holding read may
    then span blocks (pads read 0), an input read must stay inside one block.
    """
    end = address + count
    last = BLOCK_STRIDE * (blocks - 1) + N_REGISTERS
    if count < 1 or address < 0 or end > last:
        raise RegisterAddressError(f"{table} registers {address}..{end - 1} outside the map 0..{last - 1}")
    if table == "input":
        offset = address % BLOCK_STRIDE
        if offset >= N_REGISTERS or _INPUT_RUN_END[offset] < offset + count:
            raise RegisterAddressError(f"input registers {address}..{end - 1} include unmapped addresses "
                                       f"(input registers mirror only the read-only holding registers)")


def _u16(x: Any, scale: float, lo: int = 0, hi: int = 65535) -> np.ndarray:
    """Scale, round half-to-even and clip; NaN reads as ``lo`` rather than as an undefined integer."""
    y = np.rint(np.asarray(x, dtype=float) * scale)
    return np.fmin(np.fmax(y, lo), hi).astype(np.int64)   # fmax/fmin, unlike clip, replace NaN


def _i16(raw: Any) -> np.ndarray:
    """Signed raw values (float) -> two's-complement 16-bit words."""
    return _u16(raw, 1.0, -32768, 32767) & 0xFFFF


def _words32(values: np.ndarray, dtype: str, word_order: str) -> np.ndarray:
    """(n,) values -> (n, 2) words in register order."""
    w = np.ascontiguousarray(values, dtype=dtype).view(">u2").reshape(-1, 2).astype(np.int64)
    return w[:, ::-1] if word_order == CDAB else w


def encode(state: Any, scaling: Scaling, *, tick: int, overruns: int, time: float,
           out: np.ndarray | None = None) -> np.ndarray:
    """Register words of every unit: array (n, N_REGISTERS) of int64 in 0..65535.

    Parameters
    ----------
    state : object with arrays (n,) ``op, mv, flow, pv, sp, kc, ti, td, S, J`` and bool arrays
        ``stuck, sat_low, sat_high, has_controller, auto`` (a ``LoopBank`` qualifies); the instructor's
        fault arrays ``load`` (% flow), ``noise_std`` (PV units) and ``frozen`` (bool) are optional and
        read as zero when the state has none.
    scaling : the per-unit :class:`Scaling`.
    tick, overruns, time : device counters and simulated time (the same on every unit).
    out : optional preallocated array to fill.

    The device encodes straight into its byte image with the same compiled pass
    (:func:`valve_emulator.device.image.encode_image`); this returns that pass's words.
    """
    from valve_emulator.device.image import encode_words  # the image module builds on this one

    w = encode_words(state, scaling, tick=tick, overruns=overruns, time=time)
    if out is None:
        return w
    out[...] = w
    return out


def _ti_raw(ti: Any) -> np.ndarray:
    ti = np.asarray(ti, dtype=float)
    p_only = ~np.isfinite(ti) | (ti <= 0)
    return np.where(p_only, 0, _u16(np.where(p_only, 0.0, ti), 10, 1, 65535))


def patch(row: np.ndarray, quantity: str, value: float, scaling: Scaling, index: int) -> None:
    """Overwrite, in one unit's word ``row``, the registers that show ``quantity`` (after an accepted write)."""
    if quantity == "op":
        row[_A["op_pct"]] = _u16(value, 100, 0, 10000)
        row[_A["op_ma"]] = _u16(scaling.op_to_ma(value, np.array([index]))[0], 1000)
        row[20:22] = _words32(np.array([value]), ">f4", scaling.word_order)[0]
    elif quantity == "sp":
        row[_A["sp"]] = _i16(scaling.eng_to_raw(value, index))
        row[26:28] = _words32(np.array([value]), ">f4", scaling.word_order)[0]
    elif quantity == "auto":
        row[_A["mode"]] = int(bool(value))
        row[_A["status"]] = (row[_A["status"]] & ~int(Status.AUTO)) | (Status.AUTO if value else 0)
    elif quantity == "ti":
        row[_A["ti"]] = _ti_raw(value)
    elif quantity in ("kc", "td", "S", "J"):
        reg = _BY_NAME[quantity]
        row[reg.address] = _u16(value, reg.scale)
    elif quantity == "load":
        row[_A["load"]] = _i16(value * 100)
    elif quantity == "noise":
        row[_A["noise"]] = _u16(scaling.eng_to_raw(scaling.pv_lo[index] + value, index), 1, 0, 10000)
    elif quantity == "fault":
        row[_A["fault"]] = int(value)
        seized = Status.SEIZED if int(value) & Fault.SEIZED else 0
        row[_A["status"]] = (row[_A["status"]] & ~int(Status.SEIZED)) | seized
    else:
        raise KeyError(f"quantity {quantity!r} is not writable")


def decode_write(address: int, values: Sequence[int], scaling: Scaling, index: int, *,
                 auto: bool = False, instructor: bool = False) -> list[tuple[str, float]]:
    """Validate a write of raw ``values`` from ``address`` on unit ``index``; return the physical changes.

    Returns ``[(quantity, value), ...]`` in address order with quantity one of ``op`` (% travel), ``sp``
    (PV units), ``auto`` (bool), ``kc``, ``ti`` (s, ``inf`` = no integral), ``td`` (s), ``S``, ``J``
    (% travel), ``load`` (% flow), ``noise`` (standard deviation, PV units), ``fault`` (int, :class:`Fault`
    bits). Every register is checked before anything is returned, so a refused write changes nothing.

    Raises
    ------
    RegisterAddressError : an address outside the map.
    RegisterAccessError : read-only register; controller register on a loop without one; instructor
        register without ``instructor``; OP while the internal controller is in ``auto``.
    RegisterValueError : a raw value outside the register's range, e.g.
        ``register op_pct: 12000 out of range 0..10000``.
    """
    count = len(values)
    if count < 1 or address < 0 or address + count > N_REGISTERS:
        raise RegisterAddressError(f"holding registers {address}..{address + count - 1} outside the map "
                                   f"0..{N_REGISTERS - 1}")
    has_ctl = bool(scaling.has_controller[index])
    changes: list[tuple[str, float]] = []
    for a, raw in zip(range(address, address + count), values):
        reg = _HOLDING_AT[a]
        where = f"register {reg.name} (holding {reg.address})"
        if reg.access == R:
            raise RegisterAccessError(f"{where} is read-only")
        if reg.access == RW_CONTROLLER and not has_ctl:
            raise RegisterAccessError(f"{where} needs an internal controller; this loop has none")
        if reg.access == RW_INSTRUCTOR and not instructor:
            raise RegisterAccessError(f"{where} needs instructor write permission")
        if reg.quantity == "op" and has_ctl and auto:
            raise RegisterAccessError(f"{where} is writable only while the controller is in manual")
        raw = int(raw)
        lo, hi = _RANGE_OF.get(reg.name, lambda sc, i: (reg.lo, reg.hi))(scaling, index)
        signed = raw - 65536 if reg.type == "int16" and raw >= 32768 else raw
        if not (lo <= signed <= hi) or not (0 <= raw <= 65535):
            raise RegisterValueError(f"register {reg.name}: {signed} out of range {lo}..{hi}")
        changes.append((reg.quantity, _to_physical(reg, signed, scaling, index)))
    return changes


_RANGE_OF: Final = {  # registers whose write range depends on the loop
    "op_pct": lambda sc, i: tuple(sc.op_raw_range[i]),
    "op_ma": lambda sc, i: tuple(sc.ma_raw_range[i]),
}


def _to_physical(reg: Register, raw: int, scaling: Scaling, index: int) -> float:
    if reg.name == "op_ma":
        lo, hi = scaling.op_limits[index]
        return float(np.clip(scaling.tables[index].to_pct(raw / 1000.0), lo, hi))
    if reg.name == "sp":
        lo, hi = scaling.pv_lo[index], scaling.pv_hi[index]
        return float(lo + raw * (hi - lo) / 10000.0)
    if reg.name == "mode":
        return bool(raw)
    if reg.name == "ti" and raw == 0:
        return math.inf
    if reg.name == "noise":  # % of the PV range x 100 -> PV units, what the loop bank takes
        return raw / 10000.0 * float(scaling.pv_hi[index] - scaling.pv_lo[index])
    if reg.name == "fault":
        return int(raw)
    return raw / reg.scale


# --- documentation renderings ------------------------------------------------------------------------

_COLUMNS: Final = ("name", "table", "address", "type", "scale", "units", "access")


def registers_table(config: Any = None) -> list[dict]:
    """The map as rows with exactly the keys name, table, address, type, scale, units, access.

    ``config`` (a ``ServerConfig``, a ``LoopConfig`` or ``None``) only fills in the PV engineering units of
    the float32 copies when every loop shares them. Holding rows come first, then the input mirror.
    """
    pv_units = "PV units"
    if config is not None:
        units = {lp.plant.units for lp in getattr(config, "loops", (config,))}
        if len(units) == 1 and next(iter(units)):
            pv_units = next(iter(units))
    rows = []
    for table, regs in (("holding", REGISTERS), ("input", INPUT_REGISTERS)):
        for r in regs:
            units = pv_units if r.units == "PV units" else r.units
            rows.append(dict(zip(_COLUMNS, (r.name, table, r.address, r.type, r.scale, units, r.access))))
    return rows


def format_registers(rows: Sequence[dict], fmt: str = "md") -> str:
    """Render rows from :func:`registers_table` as ``"md"`` (Markdown table), ``"csv"`` or ``"json"``."""
    if fmt == "json":
        return json.dumps(list(rows), indent=2) + "\n"
    if fmt == "csv":
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=_COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        return buf.getvalue()
    if fmt == "md":
        cells = [list(_COLUMNS)] + [[str(row[c]) for c in _COLUMNS] for row in rows]
        widths = [max(len(r[j]) for r in cells) for j in range(len(_COLUMNS))]
        line = lambda r: "| " + " | ".join(c.ljust(wd) for c, wd in zip(r, widths)) + " |"  # noqa: E731
        sep = "|" + "|".join("-" * (wd + 2) for wd in widths) + "|"
        return "\n".join([line(cells[0]), sep] + [line(r) for r in cells[1:]]) + "\n"
    raise ValueError(f"format_registers: fmt must be 'md', 'csv' or 'json', got {fmt!r}")
