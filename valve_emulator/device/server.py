"""Modbus TCP adapter: serves the register image of a :class:`~valve_emulator.device.tick.Device`.

The only module that imports pymodbus on the server side (its exception codes) or knows Modbus exception codes.

Decision: our own asyncio server and PDU decoding, pymodbus for its exception codes
-----------------------------------------------------------------------------------
pymodbus 3.16's server drops every request but the first when several frames arrive in one TCP segment
(its receive buffer is cleared on send), logs a full traceback for an unknown unit id, runs datastore
"actions" twice for function code 6 and blocks the owner's own writes to client-read-only registers. Fixing
that inside its connection and datastore classes would mean overriding private methods of several classes.
So this module runs a plain ``asyncio`` TCP server with its own MBAP framing. It also decodes the request
PDUs itself: pymodbus' decoder (:class:`pymodbus.pdu.DecodePDU`) formats every request for a debug log, logging
on or not, which cost a lockstep client more than the rest of a register write. Once
:func:`~valve_emulator.device.pdu.malformed` has checked a PDU's length, quantities and byte count, its fields
are big-endian words at fixed places, read straight from the bytes; a write's answer echoes the request (FC6)
or its first five bytes (FC16), an exception answer is the function code with bit 7 set and the code, and
the MBAP header is built as pymodbus' ``FramerSocket`` builds it (``tests/device`` compares the bytes). Read
responses are the byte count plus a slice of the precomputed big-endian register image, with no
per-register work.

Framing and connection hygiene live in :mod:`~valve_emulator.device.connection` (every complete MBAP frame
answered in order, pipelined answers in one write; fairness per event-loop turn; an error budget per
connection; a frame that is not Modbus TCP ends the connection after a short tarpit) and
:mod:`~valve_emulator.device.guard` (connection limit, idle / half-open / slow-client deadlines,
rate-limited logs). This module answers one complete frame at a time (:meth:`EmulatorServer.handle`).

Hostile input
-----------------------
Every request PDU is checked against the structure the specification prescribes for its function code
(:func:`~valve_emulator.device.pdu.malformed`: exact length, quantities 1..125 read, 1..123 written by
FC16, 1..121 written by FC23, 1..2000 bits read, 1..1968 written by FC15, byte count = 2 × quantity or
⌈bits / 8⌉, coil values 0xFF00 / 0x0000, FC8 counter requests with data 0x0000, FC43 read codes 1..4)
*before* anything decodes it, so no malformed PDU reaches a decoder (pymodbus' would log a warning per
frame) and every one is answered ``0x03``.

Function codes, all decoded here from the raw bytes: 3, 4, 6, 16, 23; 1, 2, 5, 15 (the bit tables of
:mod:`~valve_emulator.device.registers.bits`), 8 (diagnostics: sub-function 0 echoes, 0x0A clears the
counters, 0x0B..0x0E read them, :class:`DiagnosticCounters`), 22 (mask write, §6.16, checked and applied
as the FC6 write of its result) and 43 / 0x0E (device identification, :mod:`~valve_emulator.device.identity`).
A refused write is logged once per client and cause (register and exception code) per interval, with the
client's certificate subject and role over TLS (:class:`~valve_emulator.device.guard.RefusalLog`). Listening
on all interfaces logs a warning at start.

Answers (exception codes):

- unit id without a loop: ``0x0B`` gateway target device failed to respond (logged at DEBUG, no traceback).
  Only the configured unit ids answer; there is no wildcard unit. (A server process that runs one slice
  of a fleet answers the other slices' units this way too: they live behind another port.)
- units carrying several loops (blocks of 32 registers, see :mod:`~valve_emulator.device.registers`): a
  holding read may span blocks, an input read and a write must stay inside one block.
- function codes other than 1, 2, 3, 4, 5, 6, 8, 15, 16, 22, 23, 43, an FC8 sub-function other than 0 and
  0x0A..0x0E, an FC43 MEI type other than 0x0E: ``0x01`` illegal function.
- ``read_only`` mode: every write function code (5, 6, 15, 16, 22, 23) gets ``0x01`` illegal function
  (the server does not offer writing at all), and nothing changes.
- read/write outside the map, an FC4 read over an unmapped input address, a write to a read-only register,
  to a controller register of a loop without controller, to a register the client's role may not write
  (:mod:`~valve_emulator.device.roles`: on the plain port an instructor register while ``instructor_writes``
  is off or the client's IP is not in ``instructor_hosts``), or to OP while the internal
  controller is in auto, and the same for a coil that writes such a register; a coil or discrete input
  that does not exist; an FC43 object id the device does not have (individual access): ``0x02`` illegal
  data address; nothing changes.
- a value out of range, or a malformed PDU (wrong length for its function code, a quantity of 0 or above
  the limits, a byte count that disagrees with the quantity or with the bytes sent): ``0x03`` illegal
  data value; nothing changes (a multi-register write is checked completely before any of it is applied).
- an unexpected failure inside the emulator (a bug): ``0x04`` server device failure, logged with traceback.
"""

from __future__ import annotations

import asyncio
import dataclasses
import ipaddress
import logging
import re
import socket
import struct
import time
from collections.abc import Awaitable, Callable
from typing import Any

from pymodbus.constants import ExcCodes

from valve_emulator.device.comm import CommFaults, CommState
from valve_emulator.device.connection import SOCKET_BUFFER, ModbusConnection, TurnBudget
from valve_emulator.device.guard import ConnectionGuard, RefusalLog, binds_all_interfaces
from valve_emulator.device.identity import Identity
from valve_emulator.device.pdu import (
    BIT_READ_FUNCTIONS,
    BIT_WRITE_FUNCTIONS,
    COUNTER_SUBFUNCTIONS,
    MEI_DEVICE_ID,
    WRITE_FUNCTIONS,
    malformed,
    write_target,
)
from valve_emulator.device.registers import (
    BLOCK_STRIDE,
    CLOCK_REGISTERS,
    COMM_BASE,
    CommFault,
    RegisterAccessError,
    RegisterAddressError,
    RegisterError,
    RegisterValueError,
    address_of,
    decode_write,
)
from valve_emulator.device.registers.bits import BitTable
from valve_emulator.device.roles import INSTRUCTOR, UNAUTHENTICATED, Role, RoleTable
from valve_emulator.device.rtu import RtuSerialLink, RtuStreamConnection, SerialSettings
from valve_emulator.device.tick import Device
from valve_emulator.device.traffic import TrafficLog, request_span
from valve_emulator.errors import UserError

__all__ = ["EmulatorServer", "LIVE_DEVICE_KEYS"]

_log = logging.getLogger(__name__)

_READS = {3: "holding", 4: "input"}
_WRITES = WRITE_FUNCTIONS
_ALL_WRITES = WRITE_FUNCTIONS | BIT_WRITE_FUNCTIONS
#: Valid register reads (unit, function, address, count) remembered for the fast path: what pollers use,
#: bounded so that a client scanning the address space cannot grow it.
_KNOWN_READS = 4096
_OWN_DECODING = BIT_READ_FUNCTIONS | BIT_WRITE_FUNCTIONS | frozenset({8, 22, 43})
_SUPPORTED = frozenset(_READS) | _ALL_WRITES | _OWN_DECODING
_STATUS_ADDRESS = address_of("status")
_CODE_OF = ((RegisterValueError, ExcCodes.ILLEGAL_VALUE), (RegisterAccessError, ExcCodes.ILLEGAL_ADDRESS),
            (RegisterAddressError, ExcCodes.ILLEGAL_ADDRESS))
_REGISTER_NAME = re.compile(r"\bregister (\w+)")
_STEP = CLOCK_REGISTERS[0]
_STEP_ADDRESS = _STEP.address.to_bytes(2, "big")   # as a request carries it

#: ``device`` settings :meth:`EmulatorServer.reconfigure` applies to a running server.
LIVE_DEVICE_KEYS = ("read_only", "instructor_writes", "instructor_hosts", "max_connections", "idle_timeout",
                    "frame_timeout", "error_rate")


class DiagnosticCounters:
    """The counters FC8 reads (serial line spec v1.02 §6.1, application protocol §6.8), modulo 2^16.

    ``bus_messages`` (0x0B): frames received; ``comm_errors`` (0x0C): frames dropped for a bad CRC or a
    silence inside them (RTU); ``exception_errors`` (0x0D): exception responses; ``server_messages``
    (0x0E): requests addressed to this server (any of its units, broadcasts included). A view of the
    server's own counters (nothing extra to count per request) since the last :meth:`clear`.
    """

    def __init__(self, server: EmulatorServer) -> None:
        self._server = server
        self._base = (0, 0, 0, 0)

    def _now(self) -> tuple[int, int, int, int]:
        s = self._server
        return (s.requests + s.foreign_frames + s.crc_errors, s.crc_errors, s.exceptions + s.fault_exceptions,
                s.requests)

    def clear(self) -> None:
        self._base = self._now()

    def read(self, sub_function: int) -> int:
        k = sub_function - 0x0B
        return (self._now()[k] - self._base[k]) & 0xFFFF

    bus_messages = property(lambda self: self.read(0x0B))
    comm_errors = property(lambda self: self.read(0x0C))
    exception_errors = property(lambda self: self.read(0x0D))
    server_messages = property(lambda self: self.read(0x0E))


class _Refused(Exception):
    """Internal: answer with exception ``code``."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code


class EmulatorServer:
    """The emulator as a Modbus TCP server: ``async with EmulatorServer(config) as srv: ...``.

    Parameters
    ----------
    config : ``ServerConfig`` (device settings and one loop per unit id).
    host, port : where to listen; ``port=0`` picks a free port, read it back from :attr:`port`.
    time_scale : see :class:`~valve_emulator.device.tick.Device` (``inf`` fastest, ``0`` frozen); a config with
        ``device.lockstep`` runs at ``0``: lockstep, the clock moves only when a client writes ``step``.
    bank : an existing ``LoopBank`` (default: built from ``config``).
    clock, sleep, jitter_size : see :class:`~valve_emulator.device.tick.Device` (fake time in tests).
    framer : ``"socket"`` (Modbus TCP, MBAP headers) or ``"rtu"`` (RTU frames with CRC over TCP, what
        gateways call RTU over TCP; :mod:`~valve_emulator.device.rtu`). :meth:`open_serial` adds a serial line.

    A bind failure raises ``OSError`` after the tick task has been stopped again. Connection limits,
    timeouts and the error budget come from ``config.device`` (``max_connections``, ``idle_timeout``,
    ``frame_timeout``, ``error_rate``) and always run on the real clock. Counters: :attr:`requests`,
    :attr:`exceptions`, :attr:`violations` (connections closed for a frame that is not Modbus TCP),
    :attr:`throttled` (times a connection ran out of its error budget), :attr:`guard` (``refused``,
    ``expired``), :attr:`refusals` (``refused`` writes).
    """

    def __init__(self, config: Any, *, host: str = "127.0.0.1", port: int = 0, time_scale: float = 1.0,
                 bank: Any = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], Awaitable[Any]] = asyncio.sleep, jitter_size: int = 4096,
                 framer: str = "socket") -> None:
        if framer not in ("socket", "rtu"):
            raise ValueError(f"framer must be 'socket' (Modbus TCP) or 'rtu' (RTU over TCP), got {framer!r}")
        self.framer = framer
        self.serial_links: list[Any] = []
        self.host = host
        self.port = port
        if config.device.lockstep:
            if config.device.read_only:
                raise UserError("device.lockstep with device.read_only (--read-only): the device would refuse the "
                                "step writes that are its clock")
            time_scale = 0.0
        self.device = Device.from_config(config, bank=bank, time_scale=time_scale, clock=clock, sleep=sleep,
                                         jitter_size=jitter_size)
        #: the register map every request is answered through (the standard one, or device.register_map)
        self.map = self.device.register_map
        self._regions = self.device.served_layout.regions   # unit -> (served image start byte, blocks)
        self._reads: dict[bytes, tuple[int, int, bytes]] = {}   # see _read_fast
        dev = config.device
        self.guard = ConnectionGuard(max_connections=dev.max_connections, idle_timeout=dev.idle_timeout,
                                     frame_timeout=dev.frame_timeout, error_rate=dev.error_rate)
        self.refusals = RefusalLog(_log)
        self._apply_access(config)
        # a unit's identity is its block 0 loop's (every unit has one: ServerConfig checks for gaps)
        self._identities = {lp.device.unit: Identity.of_loop(lp) for lp in config.loops if lp.device.block == 0}
        self.diagnostics = DiagnosticCounters(self)
        self.comm = CommFaults({unit: blocks for unit, (_, blocks) in self._regions.items()})
        if self.device.malfunctions is not None:   # the instructor's comm malfunction acts on these
            self.device.malfunctions.comm = self.comm
        self._server: asyncio.Server | None = None
        self._tls_server: asyncio.Server | None = None
        #: the Modbus/TCP Security listener's port (:meth:`open_tls`), None without one
        self.tls_port: int | None = None
        #: TLS connections whose handshake succeeded (a client certificate signed by the CA)
        self.tls_sessions = 0
        #: of those, the ones closed at once because the certificate's role is not in :attr:`roles`
        self.tls_refused = 0
        #: TLS handshakes that failed (no client certificate, one the CA did not sign, an old TLS version, ...)
        self.tls_failed = 0
        #: the TLS handshakes under way (:class:`~valve_emulator.device.tls.TlsAcceptor`)
        self.tls_handshakes: set[asyncio.Task] = set()
        self.connection_set: set[ModbusConnection] = set()
        self.turns = TurnBudget()
        self.requests = 0
        self.exceptions = 0
        self.fault_exceptions = 0     # exception answers of communication faults (not charged to a client)
        self.crc_errors = 0           # RTU frames dropped: bad CRC or a silence inside
        self.foreign_frames = 0       # RTU frames for an address not served here
        self.violations = 0
        self.throttled = 0
        #: every request answered, when a :class:`~valve_emulator.device.traffic.TrafficLog` is set (the testing
        #: kit sets one; off by default: a production server keeps no per-request rows)
        self.traffic: TrafficLog | None = None

    def _apply_access(self, config: Any) -> None:
        dev = config.device
        self.config = config
        self._read_only = bool(dev.read_only)
        self._instructor = bool(dev.instructor_writes)
        self._instructor_hosts = frozenset(_normalise_ip(h) for h in dev.instructor_hosts)
        #: the permission table of the certificates' roles (Modbus/TCP Security)
        self.roles = RoleTable.from_config(config)

    @property
    def units(self) -> tuple[int, ...]:
        return self.device.units

    @property
    def connections(self) -> int:
        """Client connections open now."""
        return len(self.connection_set)

    def instructor_allowed(self, peer_ip: str) -> bool:
        """May a client at ``peer_ip`` write the instructor registers?"""
        if not self._instructor:
            return False
        return not self._instructor_hosts or _normalise_ip(peer_ip) in self._instructor_hosts

    def plain_role(self, peer_ip: str) -> Role:
        """The role of a client without credentials (plain port, serial line) at ``peer_ip``: instructor where
        ``device.instructor_writes``/``instructor_hosts`` allow it, else :data:`UNAUTHENTICATED`."""
        return INSTRUCTOR if self.instructor_allowed(peer_ip) else UNAUTHENTICATED

    def reconfigure(self, config: Any) -> list[str]:
        """Apply the live settings (:data:`LIVE_DEVICE_KEYS`) of a new ``ServerConfig`` to the running server.

        Returns the settings that differ but need a restart (``device.tick``, ``device.word_order``, the
        loops); those keep their running values. Open connections get the new instructor permission at
        once; a lower ``max_connections`` refuses new connections but drops none.
        """
        old, new = self.config.device, config.device
        self.guard.configure(max_connections=new.max_connections, idle_timeout=new.idle_timeout,
                             frame_timeout=new.frame_timeout, error_rate=new.error_rate)
        restart = [f"device.{f.name}" for f in dataclasses.fields(new) if f.name not in LIVE_DEVICE_KEYS
                   and f.name not in ("unit", "block") and getattr(new, f.name) != getattr(old, f.name)]

        def shape(cfg: Any) -> list[tuple]:
            return [(lp.device.unit, lp.device.block, lp.name, lp.valve, lp.plant, lp.controller, lp.simulation)
                    for lp in cfg.loops]

        if shape(config) != shape(self.config):
            restart.append("loops")
        live = dataclasses.replace(old, **{k: getattr(new, k) for k in LIVE_DEVICE_KEYS})
        self._apply_access(dataclasses.replace(self.config, device=live))
        self.refusals.clear()  # new rules: report refusals under them afresh
        for conn in self.connection_set:
            conn.role = conn.permission()
        return restart

    # --- lifecycle ----------------------------------------------------------------------------------

    async def start(self) -> None:
        await self.device.start()
        try:
            loop = asyncio.get_running_loop()
            protocol = ModbusConnection if self.framer == "socket" else RtuStreamConnection
            self._server = await loop.create_server(lambda: protocol(self), self.host, self.port)
        except BaseException:
            await self.device.stop()  # no half-started server: the tick task must not outlive us
            raise
        for sock in self._server.sockets:
            # Accepted sockets inherit the listener's buffer size, and the TCP window is negotiated from
            # it during the handshake: set it here, not only after accepting (ModbusConnection does both).
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
            except OSError:
                pass
        self.guard.start()
        self.port = self._server.sockets[0].getsockname()[1]
        _log.info("serving units %s on %s:%d", list(self.units), self.host, self.port)
        if binds_all_interfaces(self.host):
            _log.warning("listening on all interfaces (%r): Modbus TCP has no authentication, anyone who can "
                         "reach port %d can read and write this device; use an isolated network",
                         self.host, self.port)

    def open_serial(self, port: str, settings: SerialSettings | None = None) -> RtuSerialLink:
        """Serve the same units as Modbus RTU on serial device ``port`` too (call after :meth:`start`; closed by
        :meth:`stop`). ``OSError`` naming the device when it cannot be opened."""
        link = RtuSerialLink(self, port, settings or SerialSettings())
        link.open()
        self.serial_links.append(link)
        return link

    async def open_tls(self, context: Any, *, host: str | None = None, port: int = 802) -> int:
        """Serve the same units as Modbus/TCP Security too: TLS with ``context``
        (:func:`~valve_emulator.device.tls.server_context`) on ``host`` (default: the plain port's) and ``port``
        (0: a free one); returns the port. Call after :meth:`start`; closed by :meth:`stop`."""
        from valve_emulator.device.tls import TlsAcceptor

        loop = asyncio.get_running_loop()
        self._tls_server = await loop.create_server(lambda: TlsAcceptor(self, context), host or self.host, port)
        self.tls_port = self._tls_server.sockets[0].getsockname()[1]
        _log.info("serving units %s over Modbus/TCP Security on %s:%d", list(self.units), host or self.host,
                  self.tls_port)
        return self.tls_port

    async def stop(self) -> None:
        server, self._server = self._server, None
        tls, self._tls_server = self._tls_server, None
        if tls is not None:
            tls.close()
            for handshake in list(self.tls_handshakes):
                handshake.cancel()
        for link in self.serial_links:
            link.close()
        self.serial_links.clear()
        self.guard.stop()
        if server is not None:
            server.close()
            for conn in list(self.connection_set):
                conn.transport.abort()
            await server.wait_closed()
        if tls is not None:
            await tls.wait_closed()
        await self.device.stop()

    async def __aenter__(self) -> EmulatorServer:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.stop()

    # --- one request --------------------------------------------------------------------------------

    def handle(self, frame: bytes, role: Role, *, peer: str = "", client: str = "") -> bytes:
        """Answer one complete MBAP ``frame`` (header + PDU) with a complete response frame.

        ``peer`` (the client's address) names the client when a refused write is logged; ``client`` (its
        ``ip:port``) names it in :attr:`traffic`.
        """
        if len(frame) == 12 and self.traffic is None:
            known = self._reads.get(frame[6:12])   # this unit, function, address and count read before
            if known is not None:
                self.requests += 1
                start, stop, head = known
                return frame[:4] + head + self.device.served[start:stop]
            if frame[7] == 3 or frame[7] == 4:
                answer = self._read_fast(frame)
                if answer is not None:
                    return answer
            elif frame[7] == 6:
                if frame[8:10] == _STEP_ADDRESS:
                    answer = self._step_fast(frame, role, peer)
                    if answer is not None:
                        return answer
                elif self._write_fast(frame, role):
                    return frame[:2] + b"\x00\x00" + frame[4:]   # the answer echoes the request
        return _mbap(frame, self.answer(frame[6], frame[7:], role, peer=peer, client=client))

    def _read_fast(self, frame: bytes) -> bytes | None:
        """The answer frame to a well-formed FC3 / FC4 read of mapped registers, straight from the register
        image's bytes; ``None`` for anything else (the general path then answers it, exceptions included).

        The same answer as the general path, without decoding into pymodbus objects and encoding back: a
        10-register read is most of what SCADA pollers send, and this halves its cost in Python. A poller
        repeats the same few reads, so each read found valid is remembered (:attr:`_reads`, at most
        :data:`_KNOWN_READS` of them; the register map of a running server never changes) and the next one
        is answered with one look-up.
        """
        region = self._regions.get(frame[6])
        address, count = (frame[8] << 8) | frame[9], (frame[10] << 8) | frame[11]
        if region is None or address >= COMM_BASE or not 1 <= count <= 125:
            return None
        start, blocks = region
        table = _READS[frame[7]]
        try:
            self.map.check_read(table, address, count, blocks=blocks)
        except RegisterError:
            return None
        self.requests += 1
        n, start = 2 * count, start + 2 * self.map.word_offset(table, address)
        # MBAP: transaction and protocol id as sent, length = unit + function + byte count + data.
        head = (n + 3).to_bytes(2, "big") + bytes((frame[6], frame[7], n))
        if len(self._reads) < _KNOWN_READS:
            self._reads[frame[6:12]] = (start, start + n, head)
        return frame[:4] + head + self.device.served[start:start + n]

    def _write_fast(self, frame: bytes, role: Role) -> bool:
        """Carry out a well-formed FC6 write of a unit register that the device accepts from the tables of its
        address (:meth:`Device.write_served_word`): ``True``. ``False``: nothing done, the general path answers
        it (refusals, the clock's registers, a read-only server, a write across blocks)."""
        region = self._regions.get(frame[6])
        address = (frame[8] << 8) | frame[9]
        if region is None or address >= COMM_BASE or self._read_only:
            return False
        try:
            index, offset = self.device.served_layout.locate_write(frame[6], address, 1)
        except RegisterError:
            return False
        if not self.device.write_served_word(index, offset, (frame[10] << 8) | frame[11], role=role):
            return False
        self.requests += 1
        return True

    def _step_fast(self, frame: bytes, role: Role, peer: str) -> bytes | None:
        """The answer frame to a well-formed FC6 write of the clock's ``step`` that the general path would carry
        out (:meth:`_step`): its ticks run, then the echo, or the exception answer to a tick that failed, as
        :meth:`_answer` gives it. ``None``: nothing done, the general path answers (refusals, with their
        messages). A lockstep client sends one of these per tick: the general path's checks cost a third of a
        tick."""
        unit = frame[6]
        if (unit not in self._regions or self._read_only or not self.comm.covers(unit, _STEP.address)
                or not role.may_write("step") or not self.device.lockstep):
            return None
        self.requests += 1
        try:
            self.device.advance((frame[10] << 8) | frame[11])
        except Exception as exc:
            return _mbap(frame, self._failed(6, unit, exc, frame[7:], peer))
        return frame[:2] + b"\x00\x00" + frame[4:]   # the answer echoes the request

    def handle_faulted(self, frame: bytes, role: Role, state: CommState, *, peer: str = "",
                       client: str = "") -> bytes | None:
        """:meth:`handle` for a unit with a communication fault (see :mod:`~valve_emulator.device.comm`):
        the response frame, or ``None`` when nothing is to be sent."""
        pdu = self.answer_faulted(frame[6], frame[7:], role, state, peer=peer, client=client)
        return None if pdu is None else _mbap(frame, pdu)

    def answer_faulted(self, unit: int, pdu: bytes, role: Role, state: CommState, *,
                       peer: str = "", client: str = "") -> bytes | None:
        """:meth:`answer` under communication fault ``state``: ``None`` for no response (and for a
        connection to be closed), an exception 0x06 / 0x04, or the normal answer (delay only, bad CRC: the
        framing corrupts it)."""
        fault = state.fault
        if fault in (CommFault.NO_RESPONSE, CommFault.CLOSE, CommFault.BUSY, CommFault.FAILURE):
            self.requests += 1
            response = None
            if fault in (CommFault.BUSY, CommFault.FAILURE):
                self.fault_exceptions += 1   # on purpose: not in self.exceptions, which the error budget charges
                code = ExcCodes.DEVICE_BUSY if fault is CommFault.BUSY else ExcCodes.DEVICE_FAILURE
                response = bytes((pdu[0] | 0x80, code))
            if self.traffic is not None:
                self.traffic.note(client, unit, pdu, response)
            return response
        return self.answer(unit, pdu, role, peer=peer, client=client)

    def broadcast(self, pdu: bytes, role: Role) -> None:
        """A broadcast write (unit 0 on a serial line): carried out by every unit, nothing answered. The clock's
        ``step`` belongs to the whole device, so a broadcast step runs its ticks once, not once per unit."""
        for n, target in enumerate(dict.fromkeys(self.units)):
            if n and pdu[0] in _ALL_WRITES and request_span(pdu)[0] == _STEP.address:
                break
            self.answer(target, pdu, role)

    def answer(self, unit: int, pdu: bytes, role: Role, *, peer: str = "", client: str = "") -> bytes:
        """The response PDU to request ``pdu`` (function code first, at least one byte) for ``unit``.

        Framing-independent: the TCP connection wraps it in MBAP, the RTU link in address and CRC.
        """
        if self.traffic is None:
            return self._answer(unit, pdu, role, peer)
        arrived = self.traffic.arrival()
        response = self._answer(unit, pdu, role, peer)
        self.traffic.note(client, unit, pdu, response, arrived=arrived)
        return response

    def _answer(self, unit: int, pdu: bytes, role: Role, peer: str) -> bytes:
        self.requests += 1
        fc = pdu[0]
        try:
            region = self._regions.get(unit)
            if region is None:
                raise _Refused(ExcCodes.GATEWAY_NO_RESPONSE, f"no loop on unit {unit}")
            if fc not in _SUPPORTED:
                raise _Refused(ExcCodes.ILLEGAL_FUNCTION, f"function code {fc} not supported")
            problem = malformed(fc, pdu)
            if problem is not None:
                raise _Refused(ExcCodes.ILLEGAL_VALUE, f"malformed request: {problem}")
            if self._read_only and fc in _ALL_WRITES:
                raise _Refused(ExcCodes.ILLEGAL_FUNCTION, "server is read-only (device.read_only)")
            if fc in _OWN_DECODING:
                return self._execute_raw(fc, pdu, unit, region, role)
            return self._execute(fc, pdu, unit, region, role)
        except Exception as exc:
            return self._failed(fc, unit, exc, pdu, peer)

    def _failed(self, fc: int, unit: int, exc: Exception, pdu: bytes, peer: str) -> bytes:
        """The exception answer to request ``pdu`` that raised ``exc`` (called in its ``except`` block)."""
        if isinstance(exc, RegisterError):
            code = next(c for cls, c in _CODE_OF if isinstance(exc, cls))
            return self._refuse(fc, code, unit, exc, pdu, peer)
        if isinstance(exc, _Refused):
            return self._refuse(fc, exc.code, unit, exc, pdu, peer)
        # a bug, not a client error: say so loudly, answer, keep serving
        _log.exception("unit %d fc %d: request failed", unit, fc)
        return self._refuse(fc, ExcCodes.DEVICE_FAILURE, unit, exc, pdu, peer)

    def _refuse(self, fc: int, code: int, unit: int, reason: Exception, pdu: bytes, peer: str) -> bytes:
        self.exceptions += 1
        _log.debug("unit %d fc %d -> exception 0x%02X: %s", unit, fc, code, reason)
        if fc in _ALL_WRITES and code != ExcCodes.GATEWAY_NO_RESPONSE and (
                isinstance(reason, RegisterError) or code == ExcCodes.ILLEGAL_FUNCTION):
            address, count = write_target(fc, pdu)
            blocked = self._regions[unit][1] > 1   # name the registers inside the loop's block
            local = address % BLOCK_STRIDE if blocked else address
            table = "coil" if fc in BIT_WRITE_FUNCTIONS else "holding"
            span = self.map.names_in(table, local, count)
            match = _REGISTER_NAME.search(str(reason))
            # one key for everything outside the map: a client scanning addresses must not flood the log
            register = match.group(1) if match else (span[0] if span else "(outside the map)")
            where = f"{table} {address}" + (f"..{address + count - 1}" if count > 1 else "")
            self.refusals.note(peer, (register, code), "refused write from %s to unit %d %s (%s): exception 0x%02X, "
                               "%s", peer or "?", unit, where, ", ".join(span) or "outside the map", code, reason)
        return bytes((fc | 0x80, code))

    def _read(self, fc: int, table: str, unit: int, region: tuple[int, int], address: int, count: int) -> bytes:
        if address >= COMM_BASE and table == "holding" and self.comm.covers(unit, address):
            if address == _STEP.address:
                _check_step(address, count)
                return bytes((fc, 2, 0, 0))   # nothing pending: a step's ticks have run before its answer
            return bytes((fc, 2 * count)) + self.comm.read(unit, address, count)
        start, blocks = region
        self.map.check_read(table, address, count, blocks=blocks)
        start += 2 * self.map.word_offset(table, address)
        return bytes((fc, 2 * count)) + self.device.served[start:start + 2 * count]

    def _write(self, unit: int, address: int, registers: Any, role: Role) -> None:
        if address >= COMM_BASE and self.comm.covers(unit, address):
            if address == _STEP.address:
                self._step(registers, role)
            else:
                self.comm.write(unit, address, registers, role=role)
            return
        index, offset = self.device.served_layout.locate_write(unit, address, len(registers))
        self.device.write_served(index, offset, registers, role=role)

    def _execute(self, fc: int, pdu: bytes, unit: int, region: tuple[int, int], role: Role) -> bytes:
        """Function codes 3, 4, 6, 16 and 23 on a well-formed ``pdu`` (its fields at the places
        :mod:`.pdu` lists)."""
        address = _u16(pdu, 1)
        if fc in _READS:
            return self._read(fc, _READS[fc], unit, region, address, _u16(pdu, 3))
        if fc == 6:
            self._write(unit, address, [_u16(pdu, 3)], role)
            return bytes(pdu)                 # the answer echoes the request
        if fc == 16:
            self._write(unit, address, _words(pdu, 6, _u16(pdu, 3)), role)
            return bytes(pdu[:5])             # function, address, count
        read_count = _u16(pdu, 3)
        if not self.comm.covers(unit, address):
            self.map.check_read("holding", address, read_count, blocks=region[1])  # refuse first
        self._write(unit, _u16(pdu, 5), _words(pdu, 10, _u16(pdu, 7)), role)
        return self._read(23, "holding", unit, region, address, read_count)

    def _step(self, registers: Any, role: Role) -> None:
        """A write of the clock's ``step`` register: run that many ticks now, before the write is answered."""
        _check_step(_STEP.address, len(registers))
        if not role.may_write("step"):
            raise RegisterAccessError(f"register step (holding {_STEP.address}) is not writable by role "
                                      f"{role.name!r}", register="step")
        if not self.device.lockstep:
            raise RegisterAccessError(f"register step (holding {_STEP.address}) is writable only in lockstep "
                                      f"(serve --lockstep); this device runs its own clock", register="step")
        self.device.advance(int(registers[0]))

    # --- the function codes decoded here (bits, diagnostics, mask write, identification) ------------

    def _status(self, unit: int, block: int) -> int:
        """The ``status`` word of the loop in ``block`` of ``unit``: the bits are views of it (the standard image
        holds it whatever map is served)."""
        at = self.device.layout.regions[unit][0] + 2 * (BLOCK_STRIDE * block + _STATUS_ADDRESS)
        return (self.device.image[at] << 8) | self.device.image[at + 1]

    def _execute_raw(self, fc: int, pdu: bytes, unit: int, region: tuple[int, int], role: Role) -> bytes:
        """Function codes 1, 2, 5, 8, 15, 22 and 43 on a well-formed ``pdu`` (see :mod:`.pdu`)."""
        if fc == 8:
            return self._diagnostics(pdu)
        if fc == 43:
            if pdu[1] != MEI_DEVICE_ID:
                raise _Refused(ExcCodes.ILLEGAL_FUNCTION, f"MEI type 0x{pdu[1]:02X} not supported")
            return self._identities[unit].response(pdu[2], pdu[3])
        address, count = _u16(pdu, 1), _u16(pdu, 3)
        if fc in BIT_READ_FUNCTIONS:
            table = BitTable.COIL if fc == 1 else BitTable.DISCRETE_INPUT
            block, bits = self.map.bits_at(table, address, count, blocks=region[1])
            status = self._status(unit, block)
            values = [bool(status & b.status) for b in bits]
            packed = bytearray((count + 7) // 8)
            for i, on in enumerate(values):
                if on:
                    packed[i >> 3] |= 1 << (i & 7)
            return bytes((fc, len(packed))) + bytes(packed)
        if fc == 22:   # result = (current AND and_mask) OR (or_mask AND NOT and_mask), §6.16
            current = int.from_bytes(self._read(3, "holding", unit, region, address, 1)[2:], "big")
            and_mask, or_mask = count, _u16(pdu, 5)
            self._write(unit, address, [(current & and_mask) | (or_mask & ~and_mask & 0xFFFF)], role)
            return bytes(pdu)
        if fc == 5:
            count, bits = 1, [pdu[3] == 0xFF]
        else:
            bits = [bool(pdu[6 + (i >> 3)] >> (i & 7) & 1) for i in range(count)]
        block, coils = self.map.bits_at(BitTable.COIL, address, count, blocks=region[1])
        index = self.device.layout.loops_of[unit][block]
        # a coil writes its standard register (mode, fault) with 0 or 1, whatever map is served
        writes = [(address_of(str(coil.register)), int(on)) for coil, on in zip(coils, bits)]
        auto = self.device.effective_auto(index)
        scaling = self.device.scaling
        for reg_address, raw in writes:   # check every coil before any is applied: whole or nothing
            decode_write(reg_address, [raw], scaling, index, auto=auto, role=role)
        for reg_address, raw in writes:
            self.device.write(index, reg_address, [raw], role=role)
        return bytes(pdu) if fc == 5 else bytes(pdu[:5])

    def _diagnostics(self, pdu: bytes) -> bytes:
        """FC8 (§6.8): sub-function 0 echoes the request; 0x0A clears and 0x0B..0x0E read the counters."""
        sub = _u16(pdu, 1)
        if sub == 0:
            return bytes(pdu)
        if sub not in COUNTER_SUBFUNCTIONS:
            raise _Refused(ExcCodes.ILLEGAL_FUNCTION, f"diagnostics sub-function 0x{sub:04X} not supported")
        if sub == 0x0A:
            self.diagnostics.clear()
            return bytes(pdu)
        return bytes(pdu[:3]) + self.diagnostics.read(sub).to_bytes(2, "big")


def _check_step(address: int, count: int) -> None:
    """A request that touches ``step`` must be that one register alone (it is not beside the unit registers)."""
    if count != 1:
        raise RegisterAddressError(f"holding registers {address}..{address + count - 1}: register step "
                                   f"(holding {_STEP.address}) is read and written alone", address=address,
                                   count=count)


def _u16(pdu: bytes, at: int) -> int:
    return (pdu[at] << 8) | pdu[at + 1]


def _words(pdu: bytes, at: int, count: int) -> list[int]:
    """``count`` big-endian 16-bit words from byte ``at`` of ``pdu``."""
    return list(struct.unpack_from(f">{count}H", pdu, at))


def _mbap(frame: bytes, pdu: bytes) -> bytes:
    """The answer frame to request ``frame``: its transaction id, protocol 0, the length, its unit, ``pdu``."""
    return frame[:2] + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big") + frame[6:7] + pdu


def _normalise_ip(host: str) -> str:
    """Canonical text of an IP address (IPv4-mapped IPv6 as IPv4); other strings unchanged."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host
    mapped = getattr(ip, "ipv4_mapped", None)
    return str(mapped or ip)
