"""The register table: one row per register, from which every encoder, decoder and check is derived.

Pure (no numpy, no pymodbus). A row says where a register lives, what it holds and how a physical value
becomes its raw word (:class:`Conversion`, ``scale``, the clip range of a reading, the range of a write).
The compiled image encoder, the Python codec (``patch``, ``decode_write``), the read checks, the
documentation tables and the clients' register specs all read these rows; nothing else states an address
or a scale. The package docstring (:mod:`valve_emulator.device.registers`) documents the map for users.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import IntEnum, IntFlag, StrEnum
from typing import Final

from valve_emulator.config.schema import BLOCK_STRIDE, MAX_BLOCKS
from valve_emulator.device.registers.errors import RegisterAddressError
from valve_emulator.device.registers.words import DataType, WordOrder

__all__ = [
    "ACCESS_VALUES",
    "BLOCK_STRIDE",
    "COMM_BASE",
    "CLOCK_REGISTERS",
    "CONTROLLER_QUANTITIES",
    "DEFAULT_PORT",
    "INPUT_REGISTERS",
    "MAP_VERSION",
    "MAX_BLOCKS",
    "MAX_DELAY_MS",
    "N_REGISTERS",
    "R",
    "REGISTERS",
    "RW",
    "RW_CONTROLLER",
    "RW_INSTRUCTOR",
    "STEP_ADDRESS",
    "UNIT_REGISTERS",
    "WRITABLE_QUANTITIES",
    "Access",
    "AlarmBit",
    "CommFault",
    "Conversion",
    "Fault",
    "Register",
    "Status",
    "address_of",
    "check_read",
    "holding_at",
    "register",
    "showing",
]

#: TCP port `valve-emulator serve` listens on by default (clients default to it too).
DEFAULT_PORT: Final = 5020
MAP_VERSION: Final = 3   # 2: load, noise, fault registers; instructor rows mirrored as input; 3: alarms


class Access(StrEnum):
    """Who may write a register."""

    R = "R"                           # nobody: read only
    RW = "RW"                         # any client (OP: only while an internal controller is in manual)
    RW_CONTROLLER = "RW-controller"   # only on a loop with an internal controller; reads 0 on the others
    RW_INSTRUCTOR = "RW-instructor"   # only a client the server allows instructor writes


R: Final = Access.R
RW: Final = Access.RW
RW_CONTROLLER: Final = Access.RW_CONTROLLER
RW_INSTRUCTOR: Final = Access.RW_INSTRUCTOR
ACCESS_VALUES: Final = tuple(Access)


class Conversion(StrEnum):
    """How the physical value ``x`` of a loop becomes the raw word (before rounding and clipping).

    ``lo, hi`` is the loop's ``plant.pv_range``; ``mA(x)`` its ``valve.ma_table``.
    """

    LINEAR = "linear"                 # raw = x · scale (float32 rows: the value itself, scale 1)
    PV_RANGE = "pv_range"             # raw = (x − lo) · 100·scale / (hi − lo): % of the PV range × scale
    PV_SPAN = "pv_span"               # a width in PV units, encoded like the PV ``lo + x`` (0 reads 0)
    LOOP_CURRENT = "loop_current"     # raw = mA(x) · scale: the OP as a loop current
    FLAG = "flag"                     # raw = 1 if x else 0
    BITS = "bits"                     # raw = x, an integer bit set
    COUNTER = "counter"               # raw = x modulo the type's range (a counter that wraps)
    COUNTS = "counts"                 # raw = lo + (x − e_lo)·(hi − lo)/(e_hi − e_lo): ``counts`` over ``span``
                                      # (a configured map's ``raw: [lo, hi]``; span None: the loop's PV range)


class Status(IntFlag):
    """Bits of the ``status`` register."""

    STUCK = 1           # valve at rest (stiction holds it)
    MOVING = 2          # valve moving (the complement of STUCK)
    SAT_LOW = 4         # OP clipped at 0 %
    SAT_HIGH = 8        # OP clipped at 100 %
    CONTROLLER = 16     # the loop has an internal PI(D) controller
    AUTO = 32           # that controller is in auto
    SEIZED = 64         # instructor fault: the valve is seized (``fault`` bit 0), it does not move at all


class AlarmBit(IntFlag):
    """Bits of the ``alarms`` register: the loop's PV alarm (:mod:`valve_emulator.device.alarms`)."""

    PV_HIGH = 1         # PV above its high alarm limit (plant.alarms)
    PV_LOW = 2          # PV below its low alarm limit
    UNACKED = 4         # not acknowledged since it became active (still set once PV is back: "returned")


class CommFault(IntEnum):
    """Values of the unit register ``comm_fault``: what the unit does to a request (see
    :mod:`valve_emulator.device.comm`; requests for the unit registers themselves are always answered)."""

    NONE = 0
    NO_RESPONSE = 1      # the request is swallowed: the client times out
    BUSY = 2             # exception 0x06 server device busy
    FAILURE = 3          # exception 0x04 server device failure
    CLOSE = 4            # the connection is closed (TCP); no response on a serial line
    BAD_CRC = 5          # the response goes out with a corrupted CRC (RTU framings; Modbus TCP answers)


class Fault(IntFlag):
    """Bits of the instructor's ``fault`` register (bits not listed here are refused)."""

    SEIZED = 1          # the valve sticks completely, whatever OP does


@dataclass(frozen=True, slots=True)
class Register:
    """One row of the map.

    Parameters
    ----------
    name, address : the register's name and zero-based address inside a loop's block.
    type : :class:`~valve_emulator.device.registers.words.DataType`; 32-bit types take two registers.
    scale : raw units per physical unit (see ``conversion``); 1 for float32, bits and counters.
    units : physical units, for the documentation.
    access : :class:`Access`.
    quantity : the model value it carries (``op``, ``pv``, ``kc`` …); several registers may show one.
    write : ``(lo, hi)`` raw range a write may take (signed for ``int16``); ``op_pct``/``op_ma`` narrow it
        per loop to the controller's ``op_limits`` (see :class:`~.scaling.Scaling`).
    read : ``(lo, hi)`` raw range a reading is clipped to; default the type's range.
    conversion : :class:`Conversion` from the physical value to the raw word.
    zero_is_off : raw 0 means "off" (``ti``: no integral action, ``inf``); a value that is not finite and
        positive reads 0, the others read at least 1.
    counts, span : with :attr:`Conversion.COUNTS`, the raw ``(lo, hi)`` the engineering ``span`` maps onto
        (``span`` None: the loop's ``plant.pv_range``).
    word_order : of a 32/64-bit register; ``None`` takes the device's (every row of the standard map).
    table : ``holding`` or ``input``, the table the row is served in.
    """

    name: str
    address: int
    type: DataType
    scale: int
    units: str
    access: Access
    quantity: str
    write: tuple[int, int] = field(default=(0, 0), kw_only=True)
    read: tuple[int, int] | None = field(default=None, kw_only=True)
    conversion: Conversion = field(default=Conversion.LINEAR, kw_only=True)
    zero_is_off: bool = field(default=False, kw_only=True)
    counts: tuple[float, float] | None = field(default=None, kw_only=True)
    span: tuple[float, float] | None = field(default=None, kw_only=True)
    word_order: WordOrder | None = field(default=None, kw_only=True)
    table: str = field(default="holding", kw_only=True)

    @property
    def width(self) -> int:
        """Number of 16-bit registers."""
        return self.type.width

    @property
    def lo(self) -> int:
        """Smallest raw value a write may take."""
        return self.write[0]

    @property
    def hi(self) -> int:
        """Largest raw value a write may take."""
        return self.write[1]

    @property
    def read_range(self) -> tuple[int, int]:
        """Raw range a reading is clipped to (``read``, or the type's range)."""
        if self.read is not None:
            return self.read
        assert self.type.raw_range is not None, f"register {self.name}: a float has no raw range"
        return (1 if self.zero_is_off else self.type.raw_range[0]), self.type.raw_range[1]


_U16, _I16, _U32, _F32 = DataType.UINT16, DataType.INT16, DataType.UINT32, DataType.FLOAT32
_PCT: Final = (0, 10000)   # 0..100 % as % × 100

REGISTERS: Final[tuple[Register, ...]] = (
    #        name      addr type scale units              access         quantity
    Register("op_pct", 0, _U16, 100, "% travel", RW, "op", write=_PCT, read=_PCT),  # write: per loop, see
    Register("op_ma", 1, _U16, 1000, "mA", RW, "op", write=(4000, 20000),           # Scaling.op_limits
             conversion=Conversion.LOOP_CURRENT),
    Register("mv_pct", 2, _U16, 100, "% travel", R, "mv", read=_PCT),
    Register("flow_pct", 3, _U16, 100, "% flow", R, "flow", read=_PCT),
    Register("pv", 4, _I16, 100, "% of pv_range", R, "pv", conversion=Conversion.PV_RANGE),
    Register("sp", 5, _I16, 100, "% of pv_range", RW_CONTROLLER, "sp", write=_PCT,
             conversion=Conversion.PV_RANGE),
    Register("mode", 6, _U16, 1, "0 manual, 1 auto", RW_CONTROLLER, "auto", write=(0, 1),
             conversion=Conversion.FLAG),
    Register("kc", 7, _U16, 1000, "% per PV unit", RW_CONTROLLER, "kc", write=(1, 65535)),
    Register("ti", 8, _U16, 10, "s (0 = no integral)", RW_CONTROLLER, "ti", write=(0, 65535), zero_is_off=True),
    Register("td", 9, _U16, 10, "s", RW_CONTROLLER, "td", write=(0, 65535)),
    Register("S", 10, _U16, 100, "% travel", RW_INSTRUCTOR, "S", write=_PCT),
    Register("J", 11, _U16, 100, "% travel", RW_INSTRUCTOR, "J", write=_PCT),
    Register("status", 12, _U16, 1, "bits", R, "status", conversion=Conversion.BITS),
    Register("map_version", 13, _U16, 1, "", R, "map_version", conversion=Conversion.BITS),
    Register("tick", 14, _U32, 1, "ticks", R, "tick", conversion=Conversion.COUNTER),
    Register("overruns", 16, _U32, 1, "ticks", R, "overruns", conversion=Conversion.COUNTER),
    Register("time", 18, _F32, 1, "s", R, "time"),
    Register("op_f32", 20, _F32, 1, "% travel", R, "op"),
    Register("mv_f32", 22, _F32, 1, "% travel", R, "mv"),
    Register("pv_f32", 24, _F32, 1, "PV units", R, "pv"),
    Register("sp_f32", 26, _F32, 1, "PV units", R, "sp"),
    # instructor fault injection: written by the training-scenario player, read by everyone
    Register("load", 28, _I16, 100, "% flow", RW_INSTRUCTOR, "load", write=(-10000, 10000)),
    Register("noise", 29, _U16, 100, "% of pv_range", RW_INSTRUCTOR, "noise", write=_PCT, read=_PCT,
             conversion=Conversion.PV_SPAN),
    Register("fault", 30, _U16, 1, "bits", RW_INSTRUCTOR, "fault", write=(0, 1),
             conversion=Conversion.BITS),
    Register("alarms", 31, _U16, 1, "bits", R, "alarms", conversion=Conversion.BITS),   # see AlarmBit
)
#: First address of the unit registers and the largest ``comm_delay_ms``.
COMM_BASE: Final = 0xFF00
MAX_DELAY_MS: Final = 10_000
#: Registers of a unit id rather than of a loop: communication faults, at fixed addresses above the blocks.
UNIT_REGISTERS: Final[tuple[Register, ...]] = (
    Register("comm_fault", COMM_BASE, _U16, 1, "0..5, see CommFault",
             RW_INSTRUCTOR, "comm_fault", write=(0, max(CommFault)), conversion=Conversion.BITS),
    Register("comm_delay_ms", COMM_BASE + 1, _U16, 1, "ms added to every answer", RW_INSTRUCTOR,
             "comm_delay_ms", write=(0, MAX_DELAY_MS)),
)
#: The device's clock, answered by every unit id: writing ``step`` = N runs N ticks of the whole device before the
#: write is answered (lockstep only: ``serve --lockstep``, see :mod:`valve_emulator.device.tick`); it reads 0.
STEP_ADDRESS: Final = COMM_BASE + 0x10
CLOCK_REGISTERS: Final[tuple[Register, ...]] = (
    Register("step", STEP_ADDRESS, _U16, 1, "ticks to run (lockstep)", RW, "step", write=(0, 0xFFFF),
             conversion=Conversion.COUNTER),
)
# Input registers mirror what a controller cannot write: the read-only rows and the instructor rows.
INPUT_REGISTERS: Final = tuple(replace(r, table="input") for r in REGISTERS if r.access in (R, RW_INSTRUCTOR))
N_REGISTERS: Final = REGISTERS[-1].address + REGISTERS[-1].width
assert N_REGISTERS <= BLOCK_STRIDE  # a block must hold the whole map
#: Quantities of the internal controller: their registers read 0 on a loop without one.
CONTROLLER_QUANTITIES: Final = frozenset(r.quantity for r in REGISTERS if r.access is RW_CONTROLLER)
#: Quantities a client may change (through any register that shows them).
WRITABLE_QUANTITIES: Final = frozenset(r.quantity for r in REGISTERS if r.access is not R)

_BY_NAME: Final = {r.name: r for r in REGISTERS}
_HOLDING_AT: Final = {r.address + w: r for r in REGISTERS for w in range(r.width)}
_SHOWING: Final = {q: tuple(r for r in REGISTERS if r.quantity == q) for q in {r.quantity for r in REGISTERS}}
# _INPUT_RUN_END[a]: first address after the run of mapped input registers starting at a (a if unmapped);
# lets the adapter validate any FC4 read with one comparison.
_INPUT_MAPPED: Final = [any(r.address <= a < r.address + r.width for r in INPUT_REGISTERS)
                        for a in range(N_REGISTERS)] + [False]
_INPUT_RUN_END: Final = list(range(N_REGISTERS + 1))
for _a in range(N_REGISTERS - 1, -1, -1):
    if _INPUT_MAPPED[_a]:
        _INPUT_RUN_END[_a] = _INPUT_RUN_END[_a + 1] if _INPUT_MAPPED[_a + 1] else _a + 1


def register(name: str) -> Register:
    """The row of register ``name`` (``KeyError`` naming it and the known names when unknown)."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"no register named {name!r}; known: {', '.join(_BY_NAME)}") from None


def address_of(name: str) -> int:
    """Zero-based address of register ``name`` (``KeyError`` naming it when unknown)."""
    return register(name).address


def holding_at(address: int) -> Register:
    """The holding register that covers ``address`` (0 .. N_REGISTERS − 1; ``KeyError`` otherwise)."""
    return _HOLDING_AT[address]


def showing(quantity: str) -> tuple[Register, ...]:
    """The registers that show ``quantity`` (empty when none does)."""
    return _SHOWING.get(quantity, ())


def check_read(table: str, address: int, count: int, *, blocks: int = 1) -> None:
    """Raise :class:`RegisterAddressError` unless ``count`` registers from ``address`` are all mapped.

    ``blocks`` is the number of loops behind the unit (see *Many loops per unit id*): a holding read may
    then span blocks (pads read 0), an input read must stay inside one block.
    """
    end = address + count
    last = BLOCK_STRIDE * (blocks - 1) + N_REGISTERS
    if count < 1 or address < 0 or end > last:
        raise RegisterAddressError(f"{table} registers {address}..{end - 1} outside the map 0..{last - 1}",
                                   address=address, count=count)
    if table == "input":
        offset = address % BLOCK_STRIDE
        if offset >= N_REGISTERS or _INPUT_RUN_END[offset] < offset + count:
            raise RegisterAddressError(f"input registers {address}..{end - 1} include unmapped addresses "
                                       f"(input registers mirror only the read-only holding registers)",
                                       address=address, count=count)
