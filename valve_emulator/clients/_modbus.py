"""What every client shares: register specs, decoding, grouped reads, a reconnecting Modbus TCP link.

A *point* says where one value lives on a device and how its raw words become a number::

    SPEC  :=  NAME                                     a register of the emulator's map (valve-emulator registers)
           |  TABLE:ADDRESS[:TYPE[:SCALE[:OFFSET]]]    any device
           |  TABLE:ADDRESS:bitN                       one bit of a 16-bit register (0/1)
    TABLE :=  holding | hr | input | ir                function code 3 or 4
    TYPE  :=  uint16 (default) | int16 | uint32 | int32 | float32 | float64

``value = (raw - OFFSET) / SCALE`` when reading and ``raw = round(value * SCALE + OFFSET)`` when writing
(SCALE default 1, OFFSET default 0). Addresses are zero-based PDU addresses (mbpoll ``-0``). Examples:
``pv_f32`` (the emulator's PV, float32, engineering units), ``input:24:float32`` (the same from the input
table), ``holding:1:uint16:160:4000`` (OP in % written as a 4-20 mA loop current in µA: ``1000·(4 + 0.16·OP)``).

32-bit values use one word order for the whole device: ``ABCD`` (high word first, the emulator's default,
mbpoll ``-B``) or ``CDAB`` (low word first, mbpoll's default). Types, word order and the emulator's named
registers all come from the register map (:mod:`valve_emulator.device.registers`), so a client reads a
register exactly as the device encodes it.

:class:`Reader` reads a set of points with as few requests as possible: points of one table closer than
``max_gap`` registers share one request, so values that come from the same request are one consistent
snapshot of the device (the emulator updates its whole register image at once per tick). A device that
refuses a read across unmapped addresses (exception 2) makes the reader fall back to one request per run
of adjacent points, once, for good.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any, Final

import numpy as np
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from valve_emulator.device.pdu import MAX_READ
from valve_emulator.device.registers import (
    ABCD,
    CDAB,
    DEFAULT_PORT,
    REGISTERS,
    DataType,
    Register,
    WordOrder,
    from_words,
    to_words,
)
from valve_emulator.errors import UserError

__all__ = [
    "ABCD",
    "CDAB",
    "TYPES",
    "DEFAULT_PORT",
    "Point",
    "Reader",
    "Link",
    "ConnectionSettings",
    "connection_from_args",
    "DeviceError", "DeviceTimeError",
    "parse_point",
    "add_connection_arguments",
    "check_connection_arguments",
]

#: type name -> (registers, struct format), from the register map's data types
TYPES: Final = {t.value: (t.width, t.struct_format) for t in DataType}
_TABLES: Final = {"holding": "holding", "hr": "holding", "input": "input", "ir": "input"}
_EXCEPTIONS: Final = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                      4: "server device failure", 6: "server busy", 10: "gateway path unavailable",
                      11: "gateway target device failed to respond"}


class DeviceTimeError(OSError):
    """The device's time went backwards under a recording (it restarted)."""


class DeviceError(OSError):
    """The device answered a request with a Modbus exception; ``code`` is the exception code."""

    def __init__(self, what: str, code: int) -> None:
        self.code = code
        super().__init__(f"{what}: exception 0x{code:02X} ({_EXCEPTIONS.get(code, 'unknown')})")


@dataclass(frozen=True)
class Point:
    """Where a value lives and how to scale it (see the module docstring); ``text`` is the spec as given."""

    table: str
    address: int
    type: str = "uint16"
    scale: float = 1.0
    offset: float = 0.0
    bit: int | None = None
    text: str = ""

    @classmethod
    def from_register(cls, reg: Register, *, table: str = "holding") -> Point:
        """The point of one of the emulator's registers: its address, type and scale (raw / scale)."""
        return cls(table, reg.address, reg.type.value, float(reg.scale), 0.0, None, reg.name)

    @property
    def width(self) -> int:
        return TYPES[self.type][0]

    def decode(self, words: Sequence[int], word_order: str = ABCD) -> float:
        """Value from this point's ``width`` raw words."""
        if self.bit is not None:
            return float((int(words[0]) >> self.bit) & 1)
        raw = from_words(words[: self.width], self.type, word_order)
        if self.type == "float32" and math.isfinite(raw):
            # the decimal the float32 stands for (12.3, not 12.300000190734863): shortest round trip
            raw = float(str(np.float32(raw)))
        return (float(raw) - self.offset) / self.scale

    def encode(self, value: float, word_order: str = ABCD) -> list[int]:
        """Raw words for ``value``; ``UserError`` naming the point when it does not fit the type."""
        if self.bit is not None or self.table != "holding":
            raise UserError(f"{self.text or self}: only holding registers (not bits) can be written")
        raw: float = value * self.scale + self.offset
        limits = DataType(self.type).raw_range
        if limits is not None:
            raw = int(round(raw))
            lo, hi = limits
            if not lo <= raw <= hi:
                raise UserError(f"{self.text}: {value!r} gives raw {raw}, outside {self.type} {lo}..{hi}")
        return to_words(raw, self.type, word_order)


def parse_point(text: str, *, what: str = "register") -> Point:
    """Parse a SPEC (module docstring); ``UserError`` naming ``what`` and the text when it is wrong."""
    spec = text.strip()
    named = {r.name: r for r in REGISTERS}
    if spec in named:
        return Point.from_register(named[spec])
    parts = spec.split(":")
    bad = (f"{what}: {text!r} is neither a register of the emulator's map ({', '.join(named)}) nor "
           "TABLE:ADDRESS[:TYPE[:SCALE[:OFFSET]]] / TABLE:ADDRESS:bitN with TABLE holding|hr|input|ir")
    if len(parts) < 2 or parts[0].lower() not in _TABLES:
        raise UserError(bad)
    table = _TABLES[parts[0].lower()]
    try:
        address = int(parts[1], 0)
    except ValueError:
        raise UserError(f"{what}: address {parts[1]!r} in {text!r} is not an integer") from None
    if not 0 <= address <= 0xFFFF:
        raise UserError(f"{what}: address {address} in {text!r} is outside 0..65535")
    if len(parts) == 3 and parts[2].lower().startswith("bit"):
        try:
            bit = int(parts[2][3:])
        except ValueError:
            bit = -1
        if not 0 <= bit <= 15:
            raise UserError(f"{what}: {parts[2]!r} in {text!r} must be bit0..bit15")
        return Point(table, address, "uint16", 1.0, 0.0, bit, spec)
    kind = parts[2].lower() if len(parts) > 2 and parts[2] else "uint16"
    if kind not in TYPES:
        raise UserError(f"{what}: type {kind!r} in {text!r} must be one of {', '.join(TYPES)}")
    if len(parts) > 5:
        raise UserError(bad)
    try:
        scale = float(parts[3]) if len(parts) > 3 and parts[3] else 1.0
        offset = float(parts[4]) if len(parts) > 4 and parts[4] else 0.0
    except ValueError:
        raise UserError(f"{what}: scale/offset in {text!r} must be numbers") from None
    if not (math.isfinite(scale) and scale != 0 and math.isfinite(offset)):
        raise UserError(f"{what}: scale must be finite and nonzero, offset finite, in {text!r}")
    if address + TYPES[kind][0] > 0x10000:
        raise UserError(f"{what}: {text!r} runs past address 65535")
    return Point(table, address, kind, scale, offset, None, spec)


@dataclass(frozen=True)
class _Request:
    table: str
    address: int
    count: int
    members: tuple[tuple[str, Point], ...]


def _plan(points: Mapping[str, Point], max_gap: int) -> list[_Request]:
    """Group points into read requests: same table, gap <= max_gap registers, <= 125 registers each."""
    requests: list[_Request] = []
    for table in ("holding", "input"):
        items = sorted(((n, p) for n, p in points.items() if p.table == table), key=lambda np_: np_[1].address)
        group: list[tuple[str, Point]] = []
        start = end = 0
        for name, p in items:
            p_end = p.address + p.width
            if group and p.address - end <= max_gap and max(end, p_end) - start <= MAX_READ:
                group.append((name, p))
                end = max(end, p_end)
                continue
            if group:
                requests.append(_Request(table, start, end - start, tuple(group)))
            group, start, end = [(name, p)], p.address, p_end
        if group:
            requests.append(_Request(table, start, end - start, tuple(group)))
    return requests


class Link:
    """One Modbus TCP connection to one unit, reconnecting on demand.

    Transport failures raise ``ConnectionError`` (an ``OSError``), exception responses :class:`DeviceError`.
    """

    def __init__(self, host: str, port: int, unit: int, *, timeout: float = 1.0) -> None:
        self.host, self.port, self.unit, self.timeout = host, int(port), int(unit), float(timeout)
        self._client: AsyncModbusTcpClient | None = None

    async def connect(self) -> None:
        """Connect (again); ``ConnectionError`` naming host and port when nobody answers."""
        self.close()
        client = AsyncModbusTcpClient(self.host, port=self.port, timeout=self.timeout, retries=0,
                                      reconnect_delay=0)
        if not await client.connect():
            client.close()
            raise ConnectionError(f"no Modbus TCP server at {self.host}:{self.port}")
        self._client = client

    def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()

    @property
    def connected(self) -> bool:
        return self._client is not None and self._client.connected

    async def _call(self, what: str, method: str, *args, **kwargs) -> list[int]:
        if not self.connected:
            await self.connect()
        assert self._client is not None
        try:
            rr = await getattr(self._client, method)(*args, device_id=self.unit, **kwargs)
        except ModbusException as exc:  # timeout or dropped connection: reconnect at the next call
            self.close()
            raise ConnectionError(f"{what} on {self.host}:{self.port} unit {self.unit}: {exc}") from None
        if rr.isError():
            raise DeviceError(f"{what} on unit {self.unit}", getattr(rr, "exception_code", 0))
        return list(getattr(rr, "registers", None) or [])

    async def read(self, table: str, address: int, count: int) -> list[int]:
        method = "read_holding_registers" if table == "holding" else "read_input_registers"
        return await self._call(f"read {table} {address}..{address + count - 1}", method, address, count=count)

    async def write(self, address: int, words: Sequence[int]) -> None:
        """Write holding registers (function code 16, also for one register)."""
        await self._call(f"write holding {address}..{address + len(words) - 1}", "write_registers", address,
                         [int(w) for w in words])

    async def write_read(self, address: int, words: Sequence[int], read_address: int, read_count: int) -> list[int]:
        """Write, then read in the same request (function code 23): the read shows the state at the write."""
        return await self._call(f"write holding {address}..{address + len(words) - 1}", "readwrite_registers",
                                read_address=read_address, read_count=read_count, write_address=address,
                                values=[int(w) for w in words])


class Reader:
    """Reads a named set of points from a :class:`Link` with few requests (see the module docstring)."""

    def __init__(self, points: Mapping[str, Point], *, word_order: str = ABCD, max_gap: int = 8) -> None:
        try:
            order = WordOrder(word_order)
        except ValueError:
            raise UserError(f"word order must be ABCD or CDAB, got {word_order!r}") from None
        if max_gap < 0:
            raise UserError(f"max_gap must be >= 0, got {max_gap}")
        self.points = dict(points)
        self.word_order = order
        self.max_gap = max_gap
        self.requests = _plan(self.points, max_gap)

    async def read(self, link: Link) -> dict[str, float]:
        """One value per point name."""
        out: dict[str, float] = {}
        for req in list(self.requests):
            try:
                words = await link.read(req.table, req.address, req.count)
            except DeviceError as exc:
                if exc.code != 2 or self.max_gap == 0:
                    raise
                # The device refuses reads over addresses it does not map: read adjacent runs only.
                self.max_gap = 0
                self.requests = _plan(self.points, 0)
                return await self.read(link)
            for name, p in req.members:
                i = p.address - req.address
                out[name] = p.decode(words[i:i + p.width], self.word_order)
        return out


@dataclass(frozen=True, kw_only=True)
class ConnectionSettings:
    """Where a client's device is and how it orders 32-bit values, with the emulator's defaults: the settings of
    :func:`add_connection_arguments`' flags, which every client's options record derives from."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    unit: int = 1
    timeout: float = 1.0
    word_order: str = ABCD

    def link(self) -> Link:
        """A :class:`Link` to the unit (connected on first use)."""
        return Link(self.host, self.port, self.unit, timeout=self.timeout)


def connection_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The connection flags, as keywords of a :class:`ConnectionSettings` (or of a record derived from it)."""
    return {f.name: getattr(args, f.name) for f in fields(ConnectionSettings)}


def add_connection_arguments(p: argparse.ArgumentParser, *, defaults: bool = True) -> None:
    """``--host --port --unit --timeout --word-order`` with the emulator's defaults.

    ``defaults=False`` leaves unset flags ``None`` (for a client that merges a settings file under them).
    """
    d = {f.name: f.default for f in fields(ConnectionSettings)}
    if not defaults:
        d = dict.fromkeys(d)
    g = p.add_argument_group("connection")
    g.add_argument("--host", default=d["host"], help="Modbus TCP server (default 127.0.0.1)")
    g.add_argument("--port", type=int, default=d["port"], help=f"TCP port (default {DEFAULT_PORT})")
    g.add_argument("--unit", type=int, default=d["unit"], help="unit (slave) id (default 1)")
    g.add_argument("--timeout", type=float, default=d["timeout"], metavar="S", help="per request, s (default 1)")
    g.add_argument("--word-order", choices=tuple(WordOrder), default=d["word_order"],
                   help="32-bit values: ABCD high word first (default; the emulator's default, mbpoll -B) or "
                        "CDAB low word first (mbpoll's default)")


def check_connection_arguments(args: argparse.Namespace) -> None:
    """``UserError`` naming the flag for an impossible connection setting."""
    if not 0 <= args.port <= 65535:
        raise UserError(f"--port must be 0..65535, got {args.port}")
    if not 0 <= args.unit <= 255:
        raise UserError(f"--unit must be 0..255, got {args.unit}")
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise UserError(f"--timeout must be > 0 s, got {args.timeout}")
