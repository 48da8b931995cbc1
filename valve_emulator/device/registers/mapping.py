"""A register map as a value: which row answers at which address of which table, for one unit id.

Pure (no numpy, no pymodbus). :class:`RegisterMap` holds the rows of the four Modbus tables -- holding and
input registers (:class:`~.table.Register`), coils and discrete inputs (:class:`~.bits.Bit`) -- and answers
every question a protocol adapter asks: is this read mapped (:meth:`RegisterMap.check_read`), where do its
words lie in a loop's served row (:meth:`RegisterMap.word_offset`), which row covers an address
(:meth:`RegisterMap.row_at`), which rows show a quantity (:meth:`RegisterMap.showing`), which bits a bit
request names (:meth:`RegisterMap.bits_at`).

There are two kinds of instance and one description:

- :data:`STANDARD`, the map of :mod:`~valve_emulator.device.registers.table` (what ``valve-emulator
  registers`` prints without a configured map): holding registers 0..30 and their input mirror, the coils and
  discrete inputs of :mod:`~.bits`; it alone supports several loops per unit (blocks);
- :func:`configured`, the map a configuration's ``device.register_map`` gives
  (:mod:`valve_emulator.config.register_map`): each tag is a row of the same kind, derived from the standard
  row of the same name, moved to its address and re-typed (``int16`` … ``float64``, ``raw: [lo, hi]`` counts,
  its own word order). A tag not placed is not served.

The codec (:mod:`~.codec`) encodes and decodes the rows of either; the compiled kernel (:mod:`~.kernel`) is the
standard map's encoder, tested equal to the codec's.

A loop's *served row* holds the words of its holding registers, then those of its input registers (each table
from its lowest to its highest mapped address). The standard map's input registers are a mirror of holding
registers at the same addresses, so its two tables share one section: its served row is the 31 words of
today's image, which the kernel writes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from valve_emulator.config.register_map import BIT_TABLES, RegisterMapConfig, TagSpec
from valve_emulator.config.register_map import reference as _reference
from valve_emulator.config.schema import WordOrder
from valve_emulator.device.registers.bits import COILS, DISCRETE_INPUTS, Bit, BitTable, check_bits
from valve_emulator.device.registers.errors import RegisterAddressError
from valve_emulator.device.registers.table import (
    CLOCK_REGISTERS,
    INPUT_REGISTERS,
    REGISTERS,
    UNIT_REGISTERS,
    Access,
    Conversion,
    R,
    Register,
    check_read,
    register,
)
from valve_emulator.device.registers.words import DataType

__all__ = ["STANDARD", "TAGS", "RegisterMap", "configured", "natural_span", "register_map_of"]


@dataclass(frozen=True, eq=False)
class RegisterMap:
    """The rows of one unit id's four tables (addresses zero-based, absolute within the unit).

    Parameters
    ----------
    holding, input : register rows (:class:`~.table.Register`, ``table`` set accordingly).
    coils, discrete_inputs : bit rows (:class:`~.bits.Bit`).
    base : how the configuration wrote addresses (1: references such as 40001; 0: offsets), for display.
    standard : is this the standard map (blocks of several loops per unit, the compiled encoder)?
    source : the configuration file the map came from ("" for the standard map).
    """

    holding: tuple[Register, ...]
    input: tuple[Register, ...]
    coils: tuple[Bit, ...]
    discrete_inputs: tuple[Bit, ...]
    base: int = 1
    standard: bool = False
    source: str = ""

    def __post_init__(self) -> None:
        at: dict[str, dict[int, Any]] = {}
        for table, rows in (("holding", self.holding), ("input", self.input), ("coil", self.coils),
                            ("discrete_input", self.discrete_inputs)):
            cells = at.setdefault(table, {})
            for row in rows:
                for a in range(row.address, row.address + getattr(row, "width", 1)):
                    assert a not in cells, f"{table} {a}: {row.name} overlaps {cells[a].name}"
                    cells[a] = row
        # the standard input table mirrors holding registers: it reads their words
        mirror = all(at["holding"].get(r.address) is not None and dataclasses.replace(r, table="holding")
                     == at["holding"][r.address] for r in self.input)
        # table -> (first address, word of the row that address 0 would take): a table's words start at its first
        # address, so word_offset(table, address) = that second number + address
        sections: dict[str, tuple[int, int]] = {}
        words = 0
        for table in ("holding", "input"):
            cells = at[table]
            if table == "input" and mirror:
                sections[table] = sections["holding"]
                continue
            first = min(cells, default=0)
            sections[table] = (first, words - first)
            words += (max(cells) + 1 - first) if cells else 0
        object.__setattr__(self, "_at", at)
        object.__setattr__(self, "_sections", sections)
        object.__setattr__(self, "row_words", words)
        written: dict[str, Register] = {}
        for row in self.holding:
            if row.access is not R:
                written.setdefault(row.quantity, row)
        object.__setattr__(self, "_written", written)
        #: the quantities the map's registers show (what a tick encodes for it)
        object.__setattr__(self, "quantities", frozenset(row.quantity for row in self.holding + self.input))
        shown: dict[str, list[Register]] = {}
        for row in self.holding + (() if mirror else self.input):
            shown.setdefault(row.quantity, []).append(row)
        object.__setattr__(self, "_shown", {q: tuple(rows) for q, rows in shown.items()})

    # --- registers ------------------------------------------------------------------------------------------

    @property
    def registers(self) -> tuple[Register, ...]:
        """Every register row: holding, then input."""
        return self.holding + self.input

    def rows(self, table: str) -> tuple[Any, ...]:
        """The rows of ``table`` (``holding``, ``input``, ``coil``, ``discrete_input``)."""
        return {"holding": self.holding, "input": self.input, "coil": self.coils,
                "discrete_input": self.discrete_inputs}[table]

    def row_at(self, table: str, address: int) -> Any:
        """The row covering ``address`` of ``table``, or ``None``."""
        return self._at[table].get(address)

    def word_offset(self, table: str, address: int) -> int:
        """The word of a loop's served row that holds ``address`` of register ``table``."""
        return self._sections[table][1] + address

    def written(self, quantity: str) -> Register | None:
        """The first holding row a client writes ``quantity`` through (not read-only), or ``None``."""
        return self._written.get(quantity)

    def showing(self, quantity: str) -> tuple[Register, ...]:
        """The register rows whose words show ``quantity`` (each once: a mirror is not counted twice)."""
        return self._shown.get(quantity, ())

    def names_in(self, table: str, address: int, count: int) -> list[str]:
        """Names of the rows of ``table`` overlapping ``address .. address + count − 1``, in address order."""
        cells = self._at[table]
        names = [cells[a].name for a in range(address, address + count) if a in cells]
        return list(dict.fromkeys(names))

    def check_read(self, table: str, address: int, count: int, *, blocks: int = 1) -> None:
        """Raise :class:`~.errors.RegisterAddressError` unless ``count`` registers from ``address`` of
        ``table`` are all mapped (the standard map: see :func:`~.table.check_read`, blocks included)."""
        if self.standard:
            check_read(table, address, count, blocks=blocks)
            return
        cells = self._at[table]
        missing = next((a for a in range(address, address + count) if a not in cells), None)
        if count < 1 or missing is not None:
            raise RegisterAddressError(
                f"{table} registers {address}..{address + count - 1}: no tag at {table} {missing} "
                f"({self.reference(table, missing)}); the configured map serves only its tags",
                address=address, count=count)

    # --- bits -----------------------------------------------------------------------------------------------

    def bits_at(self, table: BitTable, address: int, count: int, *, blocks: int = 1) -> tuple[int, tuple[Bit, ...]]:
        """``(block, bit rows)`` of a request for ``count`` bits of ``table`` from ``address``;
        :class:`~.errors.RegisterAddressError` unless every one is mapped."""
        if self.standard:
            block, offset = check_bits(table, address, count, blocks=blocks)
            return block, self.rows(table.value)[offset:offset + count]
        cells = self._at[table.value]
        missing = next((a for a in range(address, address + count) if a not in cells), None)
        if count < 1 or missing is not None:
            raise RegisterAddressError(f"{table.value} {address}..{address + count - 1}: no tag at "
                                       f"{table.value} {missing} ({self.reference(table.value, missing)}); the "
                                       f"configured map serves only its tags", address=address, count=count)
        return 0, tuple(cells[a] for a in range(address, address + count))

    # --- display --------------------------------------------------------------------------------------------

    def reference(self, table: str, address: int | None) -> str:
        """``address`` as the configuration writes it: a reference (base 1) or ``table offset`` (base 0)."""
        if address is None:
            return "?"
        return _reference(table, address) if self.base == 1 else f"{table} {address}"


def _standard() -> RegisterMap:
    return RegisterMap(REGISTERS, INPUT_REGISTERS, COILS, DISCRETE_INPUTS, standard=True)


#: The map without a configured ``device.register_map``: the table of :mod:`~.table`, bit for bit.
STANDARD: Final = _standard()

#: The rows a tag name stands for: the names ``valve-emulator registers`` lists (registers and bits), and
#: ``op``, ``mv`` and ``flow`` for the quantity itself (``op`` is written like ``op_pct``).
_ALIASES: Final = {"op": "op_pct", "mv": "mv_pct", "flow": "flow_pct"}
_UNIT_NAMES: Final = frozenset(r.name for r in UNIT_REGISTERS + CLOCK_REGISTERS)
TAGS: Final = {**{r.name: r for r in REGISTERS},
               **{alias: dataclasses.replace(register(name), name=alias) for alias, name in _ALIASES.items()}}
_BIT_TAGS: Final = {b.name: b for b in COILS + DISCRETE_INPUTS}
_TYPES: Final = {t.value: t for t in DataType}
#: Engineering ranges ``raw: [lo, hi]`` scales by default (the quantity's natural span); PV and SP take the
#: loop's ``plant.pv_range`` (``None``). Other tags need ``range: [lo, hi]`` with ``raw``.
_NATURAL: Final[Mapping[str, tuple[float, float] | None]] = {
    "op": (0.0, 100.0), "mv": (0.0, 100.0), "flow": (0.0, 100.0), "S": (0.0, 100.0), "J": (0.0, 100.0),
    "load": (-100.0, 100.0), "pv": None, "sp": None}


def natural_span(quantity: str) -> tuple[float, float] | None:
    """The engineering range ``raw`` scales for ``quantity`` (``None``: the loop's PV range); ``KeyError`` when
    the quantity has none."""
    return _NATURAL[quantity]


def _register_row(spec: TagSpec, default_order: WordOrder | None) -> Register:
    """The row a register placement stands for: the standard row of the tag, moved and re-typed."""
    base = TAGS.get(spec.name)
    if base is None:
        known = ", ".join([*TAGS, *_BIT_TAGS])
        why = (" is a unit register, always served at its fixed address" if spec.name in _UNIT_NAMES else
               " is a bit: place it in a coil (0xxxx) or discrete input (1xxxx)" if spec.name in _BIT_TAGS else
               f" is not a tag of the device (tags: {known})")
        raise spec.error(f"{{key}}: {spec.name!r}{why}")
    type_ = _TYPES[spec.type]
    if spec.table == "input" and base.access not in (R, Access.RW_INSTRUCTOR):
        raise spec.error(f"{{key}}: {spec.name} is writable ({base.access.value}) and input registers are "
                         f"read-only: place it in a holding register (4xxxx)", "address")
    fields: dict[str, Any] = dict(address=spec.address, type=type_, table=spec.table,
                                  word_order=(spec.word_order or default_order) if type_.width > 1 else None)
    if spec.raw is not None:
        if base.conversion in (Conversion.FLAG, Conversion.BITS, Conversion.COUNTER):
            raise spec.error(f"{{key}}: {spec.name} is a {base.conversion.value} register; raw counts scale "
                             f"only a measured value", "raw")
        span = spec.range
        if span is None:
            if base.quantity not in _NATURAL:
                raise spec.error(f"{{key}}: {spec.name} has no natural engineering range; give range: [lo, hi] "
                                 f"(in {base.units or 'its units'}) for raw to scale", "raw")
            span = natural_span(base.quantity)
        if type_.is_float:
            raise spec.error(f"{{key}}: a {spec.type} carries the engineering value itself; raw counts need an "
                             f"integer type", "raw")
        fields.update(conversion=Conversion.COUNTS, counts=spec.raw, span=span, scale=1, read=None,
                      zero_is_off=False, write=tuple(sorted(int(c) for c in spec.raw)))
    elif type_.is_float:
        fields.update(conversion=Conversion.LINEAR, scale=1, read=None, zero_is_off=False)
    elif base.type.is_float:
        raise spec.error(f"{{key}}: {spec.name} is an engineering value; as a {spec.type} it needs raw: [lo, hi] "
                         f"counts (or type float32/float64)", "type")
    elif type_.width > 1 and base.conversion not in (Conversion.COUNTER, Conversion.BITS):
        fields.update(read=None)   # a wider integer: the type's own range
    return dataclasses.replace(base, **fields)


def _bit_row(spec: TagSpec) -> Bit:
    """The bit a coil or discrete-input placement stands for."""
    kinds = [b for b in COILS + DISCRETE_INPUTS if b.name == spec.name]
    if not kinds:
        known = ", ".join(_BIT_TAGS)
        why = (" is a register: place it in a holding (4xxxx) or input (3xxxx) register" if spec.name in TAGS
               else f" is not a bit of the device (bits: {known})")
        raise spec.error(f"{{key}}: {spec.name!r}{why}")
    if spec.table == "coil":
        coil = next((b for b in kinds if b.table is BitTable.COIL), None)
        if coil is None:
            raise spec.error(f"{{key}}: {spec.name} is read-only (a status bit) and coils are written: place it "
                             f"in a discrete input (1xxxx)", "address")
        return dataclasses.replace(coil, address=spec.address)
    shown = next(b for b in DISCRETE_INPUTS if b.name == spec.name)
    return dataclasses.replace(shown, address=spec.address)


def configured(spec: RegisterMapConfig, word_order: WordOrder) -> RegisterMap:
    """The :class:`RegisterMap` of a configuration's ``device.register_map``; ``word_order`` is the device's.

    Refuses (:class:`~valve_emulator.config.schema.ConfigError` naming the file, line and key) a tag that is
    not a tag of the device, a writable tag in an input register or a read-only bit in a coil, a scaling that
    does not fit the tag, and a tag on the fixed unit registers (65280, 65281, 65296).
    """
    default_order = spec.word_order or word_order
    tables: dict[str, list[Any]] = {"holding": [], "input": [], "coil": [], "discrete_input": []}
    fixed = {r.address: r.name for r in UNIT_REGISTERS + CLOCK_REGISTERS}
    for tag in spec.tags:
        if tag.table in BIT_TABLES:
            tables[tag.table].append(_bit_row(tag))
            continue
        row = _register_row(tag, default_order)
        clash = next((fixed[a] for a in range(row.address, row.address + row.width)
                      if a in fixed and tag.table == "holding"), None)
        if clash is not None:
            raise tag.error(f"{{key}}: holding {row.address} is the unit register {clash}, which every map "
                            f"keeps at its fixed address", "address")
        tables[tag.table].append(row)
    ordered = {t: tuple(sorted(rows, key=lambda r: r.address)) for t, rows in tables.items()}
    return RegisterMap(ordered["holding"], ordered["input"], ordered["coil"], ordered["discrete_input"],
                       base=spec.base, source=spec.source)


def register_map_of(config: Any) -> RegisterMap:
    """The map a ``ServerConfig`` (or ``LoopConfig``) serves: its ``device.register_map``, else :data:`STANDARD`."""
    device = config.device
    if device.register_map is None:
        return STANDARD
    return configured(device.register_map, device.word_order)

