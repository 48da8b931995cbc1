"""The ``device.register_map`` section: where a configuration places each tag of the device, and how.

Pure (standard library only). This module reads what the YAML says and refuses what is wrong with it alone:
an address that is not a reference of a table or lies past 65535, a type that does not fit its table (a float
in a coil), ``raw: [lo, hi]`` with ``lo == hi``, two tags on the same register. What a tag *is* (its name,
whether it may be written) is the register map's: :mod:`valve_emulator.device.registers.mapping` checks that
when it builds the served map, and names the same file, line and key (each :class:`TagSpec` keeps them).

::

    device:
      register_map:
        base: 1              # addresses are references: 40001 is holding 0, 30001 input 0 (base: 0 = offsets)
        word_order: CDAB     # default for 32-bit and 64-bit values (default: device.word_order)
        tags:
          op: {address: 40101, type: int16, raw: [0, 27648]}      # % travel as S7 analog counts
          pv: {address: 30201, type: float32, word_order: ABCD}   # PV units
          auto: [{address: 1}, {address: 10001}]                 # one tag at several places: a list

References (``base: 1``) are what an HMI tag editor shows: the table's digit (``0`` coils, ``1`` discrete
inputs, ``3`` input registers, ``4`` holding registers) followed by the one-based number, five digits up to
9999 (``40101``) and six beyond (``465001``; a coil beyond 9999 as the text ``"065001"``). With ``base: 0``
addresses are the zero-based offsets on the wire and every tag names its ``table``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from valve_emulator.config.schema import WORD_ORDERS, ConfigError, WordOrder

__all__ = ["BIT_TABLES", "REGISTER_TABLES", "TABLES", "TAG_KEYS", "TAG_TYPES", "RegisterMapConfig", "TagSpec",
           "parse_register_map", "reference"]

#: The four tables of the Modbus data model and the digit of their references.
TABLES: dict[str, int] = {"coil": 0, "discrete_input": 1, "input": 3, "holding": 4}
BIT_TABLES = ("coil", "discrete_input")
REGISTER_TABLES = ("input", "holding")
#: Types a tag may take and the registers (or bits) each occupies.
TAG_TYPES: dict[str, int] = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2, "float64": 4,
                             "bits": 1}
SECTION_KEYS = ("base", "word_order", "tags")
TAG_KEYS = ("address", "table", "type", "raw", "range", "word_order")
MAX_ADDRESS = 0xFFFF


@dataclass(frozen=True, slots=True)
class TagSpec:
    """One placement of a tag, as the configuration gives it.

    ``address`` is zero-based in ``table``; ``type`` one of :data:`TAG_TYPES`; ``raw = (lo, hi)`` the counts
    the tag's engineering ``range`` (default: the tag's own, e.g. 0..100 % for OP, ``plant.pv_range`` for PV)
    maps onto; ``word_order`` ``None`` takes the map's. ``key`` is the dotted key of the placement and
    ``source``/``line`` where it was written, so that the register map can refuse it by name.
    """

    name: str
    table: str
    address: int
    type: str
    raw: tuple[float, float] | None = None
    range: tuple[float, float] | None = None
    word_order: WordOrder | None = None
    key: str = field(default="", compare=False)
    source: str = field(default="", compare=False)
    line: int | None = field(default=None, compare=False)

    @property
    def width(self) -> int:
        """Registers (or bits) the tag occupies."""
        return TAG_TYPES[self.type]

    def error(self, detail: str, field_name: str = "") -> ConfigError:
        """A :class:`ConfigError` about this placement (or its ``field_name``), located where it was written."""
        key = f"{self.key}.{field_name}" if field_name else self.key
        return ConfigError(detail, key=key, source=self.source, line=self.line)

    def reference(self, base: int) -> str:
        """The address as the configuration writes it: a reference (``base`` 1) or ``table offset``."""
        return reference(self.table, self.address) if base == 1 else f"{self.table} {self.address}"


@dataclass(frozen=True, slots=True)
class RegisterMapConfig:
    """The ``device.register_map`` section: ``base`` (0 or 1), the default ``word_order`` (``None``: the
    device's) and every tag placement, in file order."""

    base: int
    tags: tuple[TagSpec, ...]
    word_order: WordOrder | None = None
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if self.base not in (0, 1):
            raise ConfigError(f"{{key}} must be 0 or 1, got {self.base!r}", key="register_map.base")
        if not all(isinstance(t, TagSpec) for t in self.tags):
            raise ConfigError("{key} must hold TagSpec placements", key="register_map.tags")


def reference(table: str, address: int) -> str:
    """The one-based reference of zero-based ``address`` in ``table`` (what an HMI tag editor shows: holding 0
    -> ``"40001"``; five digits while the address fits, 0..9998, six beyond: ``"465281"``)."""
    number = address + 1
    return f"{TABLES[table]}{number:04d}" if number <= 9999 else f"{TABLES[table]}{number:05d}"


def _parse_reference(value: object, key: str) -> tuple[str, int]:
    """``(table, zero-based address)`` of a one-based reference such as ``40101`` or ``"465001"``."""
    text = ""
    if isinstance(value, str):
        text = value
    elif isinstance(value, int) and not isinstance(value, bool):   # 101 is 00101: YAML drops leading zeros
        text = f"{value:05d}"
    if not text.isdigit() or len(text) not in (5, 6):
        raise ConfigError(f"{{key}} must be a reference such as 40001 (holding), 30001 (input), 10001 (discrete "
                          f"input) or 00001 (coil) with base: 1, got {value!r}", key=key)
    digit, number = int(text[0]), int(text[1:])
    table = next((t for t, d in TABLES.items() if d == digit), None)
    if table is None:
        raise ConfigError(f"{{key}} {text}: the first digit names the table (0 coil, 1 discrete input, 3 input, "
                          f"4 holding), got {digit}", key=key)
    if not 1 <= number <= MAX_ADDRESS + 1:
        raise ConfigError(f"{{key}} {text} is past the last {table.replace('_', ' ')} reference "
                          f"{reference(table, MAX_ADDRESS)} (addresses 0..65535)", key=key)
    return table, number - 1


def _integer(value: object, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ConfigError(f"{{key}} must be a whole number, got {value!r}", key=key)
    return int(value)


def _pair(value: object, key: str) -> tuple[float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 2 or not all(
            isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise ConfigError(f"{{key}} must be [lo, hi], two finite numbers, got {value!r}", key=key)
    lo, hi = float(value[0]), float(value[1])
    if lo == hi:
        raise ConfigError(f"{{key}} must have lo != hi (a range of one value cannot be scaled), got [{lo:g}, "
                          f"{hi:g}]", key=key)
    return lo, hi


def _word_order(value: object, key: str) -> WordOrder:
    if value not in WORD_ORDERS:
        raise ConfigError(f"{{key}} must be one of {', '.join(WORD_ORDERS)}, got {value!r}", key=key)
    return WordOrder(value)


def _placement(name: str, value: object, key: str, base: int) -> dict:
    """The fields of one placement (checked alone; the tag's own rules come later)."""
    if not isinstance(value, Mapping):
        raise ConfigError("{key} must be a mapping such as {address: 40001, type: uint16} (or a list of them)",
                          key=key)
    for k in value:
        if k not in TAG_KEYS:
            raise ConfigError(f"unknown key {{key}} (allowed: {', '.join(TAG_KEYS)})", key=f"{key}.{k}")
    if "address" not in value:
        raise ConfigError("missing key {key}", key=f"{key}.address")
    table = value.get("table")
    if table is not None and table not in TABLES:
        raise ConfigError(f"{{key}} must be one of {', '.join(TABLES)}, got {table!r}", key=f"{key}.table")
    if base == 1:
        table_of_ref, address = _parse_reference(value["address"], f"{key}.address")
        if table is not None and table != table_of_ref:
            raise ConfigError(f"{{key}} {table} disagrees with the reference {value['address']} "
                              f"({table_of_ref}); with base: 1 the reference names the table", key=f"{key}.table")
        table = table_of_ref
    else:
        if table is None:
            raise ConfigError(f"missing key {{key}}: with base: 0 the address is an offset, so name the table "
                              f"({', '.join(TABLES)})", key=f"{key}.table")
        address = _integer(value["address"], f"{key}.address")
        if not 0 <= address <= MAX_ADDRESS:
            raise ConfigError(f"{{key}} must be in 0..{MAX_ADDRESS}, got {address}", key=f"{key}.address")
    type_ = value.get("type", "bits" if table in BIT_TABLES else None)
    if type_ is None:
        raise ConfigError(f"missing key {{key}} (one of {', '.join(t for t in TAG_TYPES if t != 'bits')})",
                          key=f"{key}.type")
    if type_ not in TAG_TYPES:
        raise ConfigError(f"{{key}} must be one of {', '.join(TAG_TYPES)}, got {type_!r}", key=f"{key}.type")
    if (type_ == "bits") != (table in BIT_TABLES):
        fits = ("bits" if table in BIT_TABLES else
                ", ".join(t for t in TAG_TYPES if t != "bits"))
        raise ConfigError(f"{{key}} {type_} does not fit the {table.replace('_', ' ')} table at "
                          f"{reference(table, address) if base == 1 else address} (it takes {fits})",
                          key=f"{key}.type")
    width = TAG_TYPES[type_]
    if address + width - 1 > MAX_ADDRESS:
        raise ConfigError(f"{{key}}: a {type_} at {table} {address} takes {width} registers and runs past "
                          f"address {MAX_ADDRESS}", key=f"{key}.address")
    raw = None if value.get("raw") is None else _pair(value["raw"], f"{key}.raw")
    span = None if value.get("range") is None else _pair(value["range"], f"{key}.range")
    if (raw is not None or span is not None) and type_ == "bits":
        raise ConfigError("{key} scales a number; a bit is 0 or 1", key=f"{key}.{'raw' if raw else 'range'}")
    if raw is not None:
        limits = {"int16": (-32768, 32767), "uint16": (0, 65535), "int32": (-2 ** 31, 2 ** 31 - 1),
                  "uint32": (0, 2 ** 32 - 1)}.get(type_)
        if limits is not None and not all(limits[0] <= r <= limits[1] and r == int(r) for r in raw):
            raise ConfigError(f"{{key}} must be whole counts a {type_} holds ({limits[0]}..{limits[1]}), got "
                              f"[{raw[0]:g}, {raw[1]:g}]", key=f"{key}.raw")
    if span is not None and raw is None:
        raise ConfigError("{key} is the engineering range that raw: [lo, hi] scales; give raw too",
                          key=f"{key}.range")
    order = None if value.get("word_order") is None else _word_order(value["word_order"], f"{key}.word_order")
    return dict(name=name, table=table, address=address, type=type_, raw=raw, range=span, word_order=order,
                key=key)


def _overlaps(tags: list[TagSpec]) -> None:
    """Refuse two placements sharing a register (or a bit) of one table; the later one is named."""
    owner: dict[tuple[str, int], TagSpec] = {}
    for tag in tags:
        for a in range(tag.address, tag.address + tag.width):
            first = owner.get((tag.table, a))
            if first is not None:
                raise tag.error(f"{{key}} ({tag.table} {tag.address}..{tag.address + tag.width - 1}) overlaps "
                                f"{first.key} ({first.name}, {first.table} {first.address}.."
                                f"{first.address + first.width - 1}, line {first.line})", "address")
            owner[(tag.table, a)] = tag


def parse_register_map(value: object, key: str, *, source: str = "",
                       line_of: Callable[[str], int | None] = lambda key: None) -> RegisterMapConfig:
    """The :class:`RegisterMapConfig` of the YAML mapping ``value`` found at dotted ``key``.

    ``line_of(dotted key)`` gives the line a key was written on (the loader's index); every
    :class:`ConfigError` names ``source``, that line and the key.
    """
    def located(err: ConfigError) -> ConfigError:
        full = err.key if err.key.startswith(key) else f"{key}.{err.key}" if err.key else key
        return ConfigError(err.detail, key=full, source=source, line=line_of(full))

    try:
        if not isinstance(value, Mapping):
            raise ConfigError("{key} must be a mapping with base, word_order and tags", key=key)
        for k in value:
            if k not in SECTION_KEYS:
                raise ConfigError(f"unknown key {{key}} (allowed: {', '.join(SECTION_KEYS)})", key=f"{key}.{k}")
        base = value.get("base", 1)
        if base not in (0, 1) or isinstance(base, bool):
            raise ConfigError(f"{{key}} must be 0 (addresses are offsets) or 1 (references such as 40001), "
                              f"got {base!r}", key=f"{key}.base")
        order = None if value.get("word_order") is None else _word_order(value["word_order"], f"{key}.word_order")
        tags_value = value.get("tags")
        if not isinstance(tags_value, Mapping) or not tags_value:
            raise ConfigError("{key} must map tag names to placements, e.g. op: {address: 40001, type: uint16}",
                              key=f"{key}.tags")
        tags: list[TagSpec] = []
        for name, item in tags_value.items():
            tag_key = f"{key}.tags.{name}"
            items = list(enumerate(item)) if isinstance(item, list) else [(None, item)]
            if not items:
                raise ConfigError("{key} must not be an empty list", key=tag_key)
            for i, placement in items:
                at = tag_key if i is None else f"{tag_key}[{i}]"
                fields = _placement(str(name), placement, at, base)
                tags.append(TagSpec(**fields, source=source, line=line_of(f"{at}.address") or line_of(at)))
        _overlaps(tags)
    except ConfigError as err:
        raise located(err) from None
    return RegisterMapConfig(base, tuple(tags), order, source=source)
