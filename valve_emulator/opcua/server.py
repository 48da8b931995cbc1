"""OPC UA adapter: the same live loops as the Modbus server, as an OPC UA address space (asyncua).

The only module that knows OPC UA's wire format and address-space types. It serves the
:class:`~valve_emulator.device.tick.Device` that the Modbus server ticks through a
:class:`~valve_emulator.opcua.source.DeviceSource`: in the device's process and event loop
(:class:`~valve_emulator.opcua.source.LocalSource`), or in a process of its own fed from shared memory
(:mod:`valve_emulator.opcua.process`, what ``serve --opcua`` runs). Either way a value written over one protocol
is read over the other at once.

Address space (namespace ``urn:valve-emulator``)::

    Objects
    └── ValveEmulator                         the station object: Freeze, Run, SetSpeed, Snapshot, Restore,
        │                                     InjectMalfunction (instructors only)
        └── Unit1                             one object per Modbus unit id
            └── FIC101   (LoopType)           one object per loop; the type is defined once under
                ├── op, mv, flow, S, J, load  ObjectTypes/BaseObjectType/LoopType; AnalogItemType, Double,
                ├── pv, sp, noise             EngineeringUnits, EURange
                ├── kc, ti, td, time          AnalogItemType, Double, EngineeringUnits
                ├── mode, status, fault, map_version, tick, overruns    BaseDataVariableType (integers)
                └── stuck, moving, sat_low, sat_high, seized            TwoStateDiscreteType (Boolean)

Every variable is derived from the register map (:data:`~valve_emulator.device.registers.REGISTERS`): one
variable per quantity, named after the quantity's 16-bit register (``op_pct`` → ``op``), read from the
register with the finest resolution (the float32 copy where there is one) and written through the first
writable register, so an OPC UA write is checked by exactly the code that checks a Modbus write
(:meth:`Device.write <valve_emulator.device.tick.Device.write>`, in the device's process). The bits are the
``status`` register's.

Writes answer:

- ``BadNotWritable``: a read-only variable, OP while the loop is in auto, a controller variable of a loop
  without controller;
- ``BadUserAccessDenied``: a variable the user's role does not write (:mod:`valve_emulator.device.roles`:
  a viewer writes nothing, an operator OP, SP and mode; anonymous clients are operators), logged once per
  user and variable per interval;
- ``BadOutOfRange``: a value the register refuses (the Modbus ``0x03``); ``BadTypeMismatch``: not a number.

Values are read at request time from the register image (so a read sees a write at once, as over Modbus), float32
registers as the double the tick computed (:meth:`OpcUaServer.value`); subscriptions are fed after every tick with
the values that changed, each monitored item at its sampling interval (:func:`revised_sampling`: 0 is every tick, -1
the subscription's publishing interval), so a client sampling at 1 s costs one notification per item per second
whatever the tick. The values are handed half a tick after the tick, on a grid of the tick period
(:mod:`~valve_emulator.opcua.handoff`), so that each publishing interval of a subscription holds one sample of each
item whatever the tick's jitter: a queue of one loses none. Each analog item has EngineeringUnits with its UNECE
code (:mod:`~valve_emulator.opcua.units`) and, where it has one, an EURange; a value outside it is
``UncertainEngineeringUnitsExceeded``. ``SourceTimestamp`` is the wall-clock time of the tick that made the value
(:class:`TickClock`), ``ServerTimestamp`` the time it was read or, in a subscription, sampled.

Each loop's PV alarm is an ``AlarmConditionType`` condition (``Unit1.FIC101.PvAlarm``) whose events come from
the ``Server`` object and which a client acknowledges (:mod:`~valve_emulator.opcua.alarms`).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import math
import struct
import time
import weakref
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from asyncua import Server, ua
from asyncua.common.callback import CallbackType
from asyncua.server.address_space import AttributeService
from asyncua.server.monitored_item_service import MonitoredItemService

from valve_emulator.device.guard import RefusalLog, is_loopback
from valve_emulator.device.registers import (
    CDAB,
    REGISTERS,
    Conversion,
    DataType,
    R,
    Register,
    RegisterAccessError,
    RegisterError,
    RegisterValueError,
    Status,
    encode_write,
    from_words,
)
from valve_emulator.device.registers.codec import decode_value
from valve_emulator.device.roles import OPERATOR, Role
from valve_emulator.device.tick import Device
from valve_emulator.errors import UserError
from valve_emulator.opcua.alarms import AlarmConditions
from valve_emulator.opcua.handoff import HandOffGrid, Wakeups, chunk_times
from valve_emulator.opcua.history import HISTORIZED, historize, refuse_unhistorized
from valve_emulator.opcua.shared import TickImage
from valve_emulator.opcua.source import DeviceSource, LocalSource, StationRefusal, finite_period
from valve_emulator.opcua.trust import TrustList
from valve_emulator.opcua.units import eu_information
from valve_emulator.opcua.users import RoleRuleset, StationUser, UsersFile

__all__ = ["OpcUaServer", "OpcUaSecurity", "OpcUaCounters", "NAMESPACE", "VARIABLES", "BITS", "OpcUaError",
           "revised_sampling"]

_log = logging.getLogger(__name__)

NAMESPACE = "urn:valve-emulator"
APPLICATION_URI = "urn:valve-emulator:server"
#: The publisher yields to the event loop after this many monitored variables (in the device's process: the tick
#: comes first; in a process of its own it samples a tick without yielding, see ``OpcUaServer``) ...
YIELD_EVERY = 200
#: ... and, in the device's process, stops for this tick once it has used this share of the tick period (the tick
#: comes first; the variables not sampled go on at the next tick, counted in ``deferred``) ...
PUBLISH_BUDGET = 0.3
#: ... but never in a process of its own: there the tick runs in another process, and a due sample moved to the next
#: tick is moved across the publish of every item whose publish falls between the two ticks (at 1 s sampling on a
#: 0.1 s tick one item in ten), which then goes out without it and with a queue of one never carries it
#: (docs/benchmarks.md §9.12). A publisher behind the device (its pass longer than a tick) takes the newest tick
#: when it is done, unless that tick's hand-off is past by half a tick or more (``handoff.TAKE_LATE``; since
#: 2026-11-28 the OPC UA process hands ahead instead, ``hand_ahead``): then it waits for the next tick, so that a
#: publisher the machine cannot keep up with leaves the event loop to asyncua's publishes and the clients'
#: requests between ticks (the ticks it skipped counted in ``skipped``); a group due at a skipped tick is sampled at
#: the next one on its own grid (:func:`next_due`).
PROCESS_PUBLISH_BUDGET = math.inf
#: The publisher hands a tick's values in chunks of this many monitored variables ...
HAND_CHUNK = 200
#: ... each due this share of the tick period after the one before (more than a chunk's work: 200 variables take
#: 2-5 ms, a share of 0.05 is 5 ms at a 0.1 s tick), or closer where the chunks would spread over more than
#: :data:`~valve_emulator.opcua.handoff.HAND_SPREAD` of the period (more than 6 chunks: over 1,200 variables).
HAND_SPACING = 0.05
#: In a process of its own (``hand_ahead``) the hand-off chunks of this many ticks ahead are on the event loop's
#: timer heap, each sampling the shared image when it fires: so a loop held up to this many ticks (asyncua's publish
#: of thousands of values, a core not given: 0.2-0.7 s measured, docs/benchmarks.md §9.16) still runs each
#: hand-off before every publish due after it. A tick period of them, at 20 chunks (4,000 monitored variables), is
#: 200 timers; a longer hold hands the ticks past the last registered one late, as before.
HAND_AHEAD = 10
#: A hand-off whose first chunk runs this share of the period after its time on the grid is kept as handed late
#: (``OffGrid``, for ``--trace``).
HANDED_LATE = 0.1
#: A float32 register's two words (big-endian, as in the register image) and the float32 they make, high word first.
_WORDS = struct.Struct(">HH")
_FLOAT32 = struct.Struct(">f")
SECURE_POLICIES = ("Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss")


class OpcUaError(UserError):
    """A server that must not start as configured (e.g. bound beyond loopback without security)."""


#: The unit text of a variable in its loop's PV units (``plant.units``).
PV_UNITS = "PV units"
_PERCENT_UNITS = ("% travel", "% flow")


@dataclass(frozen=True)
class Variable:
    """One OPC UA variable of a loop: ``name`` (BrowseName), the quantity's 16-bit register (``first``), the
    register it is read from and the one it is written through (None: read-only), and its data type."""

    name: str
    first: Register
    read: Register
    write: Register | None
    analog: bool

    @property
    def variant(self) -> ua.VariantType:
        if self.analog:
            return ua.VariantType.Double
        return ua.VariantType.UInt32 if self.read.type is DataType.UINT32 else ua.VariantType.UInt16

    @property
    def units(self) -> str:
        """The unit the value is served in: :data:`PV_UNITS` for a PV-scaled quantity, else the register's
        unit without its remark (``ti``'s "s (0 = no integral)" is in "s")."""
        if self.first.conversion in (Conversion.PV_RANGE, Conversion.PV_SPAN) or self.read.units == PV_UNITS:
            return PV_UNITS
        units = self.read.units if self.read.type is DataType.FLOAT32 else self.first.units
        return units.split(" (")[0]

    @property
    def percent_range(self) -> tuple[float, float] | None:
        """The range of a % travel or % flow quantity: what its 16-bit register takes (written) or shows."""
        if self.units not in _PERCENT_UNITS:
            return None
        lo, hi = self.first.write if self.first.access is not R else self.first.read_range
        return lo / self.first.scale, hi / self.first.scale


def _variables() -> tuple[Variable, ...]:
    """One :class:`Variable` per quantity of the register map, in the map's order."""
    out: list[Variable] = []
    for quantity in dict.fromkeys(r.quantity for r in REGISTERS):
        showing = [r for r in REGISTERS if r.quantity == quantity]
        first = showing[0]
        read = next((r for r in showing if r.type is DataType.FLOAT32), first)
        write = next((r for r in showing if r.access is not R), None)
        analog = read.type is DataType.FLOAT32 or (first.scale > 1 and first.conversion is not Conversion.BITS)
        out.append(Variable(name=first.name.removesuffix("_pct"), first=first, read=read, write=write, analog=analog))
    return tuple(out)


#: The loop variables, derived from the register map.
VARIABLES: tuple[Variable, ...] = _variables()
#: The status bits served as TwoStateDiscrete variables: name -> (bit, TrueState, FalseState).
BITS: dict[str, tuple[Status, str, str]] = {
    "stuck": (Status.STUCK, "stuck", "free"),
    "moving": (Status.MOVING, "moving", "at rest"),
    "sat_low": (Status.SAT_LOW, "OP at 0 %", "normal"),
    "sat_high": (Status.SAT_HIGH, "OP at 100 %", "normal"),
    "seized": (Status.SEIZED, "seized", "free"),
}
_STATUS = next(v for v in VARIABLES if v.name == "status")

@dataclass(frozen=True)
class OpcUaSecurity:
    """How clients may connect.

    ``policies``: ``"None"`` and/or secure policy names (:data:`SECURE_POLICIES`, always Sign&Encrypt);
    ``certificate``/``private_key``: the application instance certificate (PEM or DER) and its key;
    ``users``: the users file's users, name -> (role of the permission table, hash) (None: anonymous
    operators only);
    ``pki``: the trust list's folder (:class:`~valve_emulator.opcua.trust.TrustList`: ``trusted/certs``,
    ``rejected/certs``), which a secure policy needs; ``trust_all``: accept every client certificate instead
    (loopback only).
    """

    policies: tuple[str, ...] = ("None",)
    certificate: Path | None = None
    private_key: Path | None = None
    users: dict | None = None
    pki: Path | None = None
    trust_all: bool = False

    def check(self, host: str) -> None:
        """Refuse a set-up that exposes the device: beyond loopback only secure policies with users."""
        unknown = [p for p in self.policies if p != "None" and p not in SECURE_POLICIES]
        if unknown:
            raise OpcUaError(f"opcua security policy {unknown[0]!r}: known are None, {', '.join(SECURE_POLICIES)}")
        secure = [p for p in self.policies if p != "None"]
        if secure and (self.certificate is None or self.private_key is None):
            raise OpcUaError(f"opcua: policy {secure[0]} needs a certificate and a private key "
                             "(make them with 'valve-emulator certs --opcua DIR')")
        if secure and self.pki is None and not self.trust_all:
            raise OpcUaError(f"opcua: policy {secure[0]} needs a trust list of client certificates (--opcua-pki "
                             "DIR or opcua.pki; unknown clients land in DIR/rejected/certs) or, on loopback, "
                             "--opcua-trust-all")
        if self.trust_all and not is_loopback(host):
            raise OpcUaError(f"--opcua-trust-all: refusing to accept every client certificate on {host!r} (beyond "
                             "loopback); trust each client by moving its certificate from PKI/rejected/certs to "
                             "PKI/trusted/certs (docs/opcua.md)")
        if is_loopback(host):
            return
        if "None" in self.policies or not secure or not self.users:
            raise OpcUaError(f"opcua: refusing to listen on {host!r} (beyond loopback) without security: configure "
                             f"a secure policy ({', '.join(SECURE_POLICIES)}, Sign&Encrypt), a certificate and a "
                             "users file, and drop policy None")


@dataclass(frozen=True)
class OffGrid:
    """A tick the publisher did not hand on its grid (:mod:`~valve_emulator.opcua.handoff`): never sampled
    (``skipped``: a newer tick had come by the time the publisher was done with the one before) or handed after its
    hand-off on the grid (the tick reached the publisher late). ``tick``: its number; ``stamp``: its time as a
    SourceTimestamp says it (POSIX seconds; a skipped tick's, the next sampled tick's less the periods between);
    ``late``: seconds past its hand-off on the grid when the publisher came to it (a skipped tick: when it was done
    with the tick before; negative: it was done in time and waited, and the tick's note came when a newer tick had
    run); ``busy``: the OPC UA process's CPU seconds per second of wall time since the tick before the publisher
    came to it arrived (near 1: the process was busy with its own work; well below 1 with the publisher behind: it
    waited for a core)."""

    tick: int
    stamp: float
    skipped: bool
    late: float
    busy: float


#: The publisher keeps the last this many :class:`OffGrid` ticks.
OFF_GRID_KEPT = 512


@dataclass(frozen=True)
class OpcUaCounters:
    """What an OPC UA server has done so far: data-change notifications handed to subscriptions (one per
    monitored item and change), ticks after which the publisher ran out of its budget (in the device's process),
    ticks the publisher never sampled because it was still busy with an earlier one (behind the device), writes
    accepted and refused, client certificates the trust list accepted and refused, alarm events sent; the last
    :data:`OFF_GRID_KEPT` ticks not handed on the grid (:class:`OffGrid`, oldest first); in the OPC UA process, the
    hand-off chunks that sampled a tick newer than their own (run after the device published the next one, the
    shared image keeping none at or before theirs) and those that sampled the same tick as that chunk of the hand-off
    before (its items sampled every tick unchanged: none handed, a publish between the two without them), and the
    thread CPU seconds its hand-off chunks took (sampling and handing to the monitored items' queues: the publisher's
    part of the cost per notification, whatever the clients take of it)."""

    notifications: int = 0
    deferred: int = 0
    skipped: int = 0
    writes: int = 0
    refused: int = 0
    trust_accepted: int = 0
    trust_refused: int = 0
    alarm_events: int = 0
    off_grid: tuple[OffGrid, ...] = ()
    sampled_newer: int = 0
    sampled_again: int = 0
    handing_cpu: float = 0.0


#: A variable's value now: (value, variant type, status: None for Good).
Sampler = Callable[[], tuple[Any, ua.VariantType, ua.StatusCode | None]]

_GOOD = ua.StatusCode(ua.StatusCodes.Good)
#: The status of an analog value outside its EURange (OPC UA Part 8: the value is outside the range defined for it).
_EU_EXCEEDED = ua.StatusCode(ua.StatusCodes.UncertainEngineeringUnitsExceeded)


class TickClock:
    """The wall-clock time of the tick that made the values served now: the SourceTimestamp.

    Where the source knows when the device ran the tick (``tick_time``: the OPC UA process, from the shared image's
    header) that is the stamp, however late this process samples it. Otherwise (in the device's process) a tick is
    stamped when the server first sees it -- the publisher waits for every tick and wakes right after it, and a
    read between the two stamps it itself -- so the stamp is the tick's time to within the event loop's latency,
    without a callback in the tick (``Device.on_tick`` would keep ``Device.advance`` from running quiet ticks as
    one compiled call). A restored snapshot counts as a new tick."""

    def __init__(self, source: DeviceSource) -> None:
        self.source = source
        self._seen: tuple[int, float] | None = None
        self._at = datetime.now(UTC)

    def stamp(self) -> datetime:
        """When the current tick ran (the device's time of it, or the first time this clock saw it)."""
        source = self.source
        seen = (source.ticks, source.sample_time)
        if seen != self._seen:
            ran = source.tick_time
            self._seen, self._at = seen, datetime.now(UTC) if ran is None else datetime.fromtimestamp(ran, UTC)
        return self._at


def revised_sampling(requested_ms: float, publishing_ms: float, tick_ms: float) -> tuple[float, float]:
    """The sampling interval a monitored item gets (OPC UA Part 4, MonitoredItem parameters): (the interval the
    publisher honours, the interval reported to the client), in ms.

    A negative (or not a number) request is the subscription's publishing interval; 0 is "the fastest practical
    rate", every tick, and so is anything shorter than a tick, reported as the tick. asyncua itself reports every
    item's sampling interval as its subscription's publishing interval and hands it every change."""
    if not math.isfinite(requested_ms) or requested_ms < 0:
        requested_ms = publishing_ms
    honoured = requested_ms if requested_ms > tick_ms else 0.0
    return honoured, max(requested_ms, tick_ms)


def next_due(due: float, now: float, interval: float) -> float:
    """When the next sample of a group sampled every ``interval`` seconds is due, after one taken at ``now`` that
    was due at ``due``: on the group's own grid, so that a late tick does not stretch the interval, or an interval
    from now when the publisher fell a whole interval behind."""
    following = due + interval
    return following if following > now else now + interval


#: The golden ratio's fraction: the phases k × _GOLDEN mod 1 of any number of variables are spread evenly.
_GOLDEN = (math.sqrt(5) - 1) / 2


def first_due(now: float, interval: float, index: int) -> float:
    """When a new group of variable ``index`` sampled every ``interval`` seconds is first due: at a phase of
    the interval that spreads the variables evenly over it (the golden ratio's fractions), so that a thousand
    loops sampled at 1 s cost a tenth of them every 0.1 s tick rather than all of them once a second. The
    items' initial values need no sample: asyncua sends them when it creates the items."""
    return now + interval * ((index * _GOLDEN) % 1.0)


class _GroupState:
    """What the publisher keeps of a group of monitored items from tick to tick: when its next sample is due (the
    event loop's clock; None: not sampled yet) and the value last handed to it (None: none yet)."""

    __slots__ = ("due", "sent")

    def __init__(self) -> None:
        self.due: float | None = None
        self.sent: Any = None


@dataclass(frozen=True)
class _Group:
    """The monitored items of one variable that share a sampling interval (s; 0: every tick): their data-change
    callbacks' handles, ``key`` (variable, interval) under which the group's :class:`_GroupState` is kept when the
    list of monitored variables is rebuilt, and that state."""

    key: tuple[int, float]
    interval: float
    handles: tuple[int, ...]
    state: _GroupState = field(default_factory=_GroupState, compare=False)


@dataclass
class _Watch:
    """A monitored variable: its value attribute (whose data-change callbacks are the monitored items), its
    sampler, its monitored items grouped by sampling interval, and the earliest due time of its groups (the
    publisher's pass skips the variable until then: at 1 s sampling nine ticks in ten; -inf: look at it)."""

    attval: Any
    sample: Sampler
    groups: tuple[_Group, ...]
    soonest: float = -math.inf


_STATUS_VALUE = ua.DataChangeTrigger.StatusValue
#: the tables of asyncua 2.1.0's MonitoredItemService that :func:`notify` reads
_SERVICE_TABLES = frozenset({"_monitored_datachange", "_monitored_items", "isub"})
_DISABLED = ua.MonitoringMode.Disabled
_IS_DATA_CHANGED = MonitoredItemService._is_data_changed
#: a handle not resolved yet (:attr:`OpcUaServer._resolved`)
_UNRESOLVED = object()


#: per monitored-item service: whether :func:`notify` may read its tables (decided at its first notification;
#: forgotten with the service, when its subscription ends)
_READABLE: weakref.WeakKeyDictionary[Any, bool] = weakref.WeakKeyDictionary()


def _readable(service: Any) -> bool:
    """Whether ``service`` (a ``MonitoredItemService``) has the tables of asyncua 2.1.0's that :func:`notify`
    reads."""
    return vars(service).keys() >= _SERVICE_TABLES and hasattr(service, "_is_data_changed")


class _Item:
    """The monitored item behind a data-change callback handle, resolved once (:func:`resolve`) rather than at each
    notification: asyncua 2.1.0's item record (``MonitoredItemData``, whose mode, filter and queue size a client's
    ModifyMonitoredItems/SetMonitoringMode change in place), its values, its id and its subscription's
    ``enqueue_datachange_event``. A handle names one item for as long as it exists (asyncua never reuses one)."""

    __slots__ = ("mdata", "values", "mid", "enqueue", "_filter", "_filtered")

    def __init__(self, mdata: Any, mid: int, enqueue: Callable[..., Any]) -> None:
        self.mdata, self.values, self.mid, self.enqueue = mdata, mdata.mvalue, mid, enqueue
        self._filter, self._filtered = mdata.filter, bool(mdata.filter)

    def filtered(self) -> bool:
        """Whether the item has a filter (a deadband): its values then go through asyncua's callback. The filter's
        truth (a Python call on an ExtensionObject) is taken again only when a client replaced it."""
        current = self.mdata.filter
        if current is not self._filter:
            self._filter, self._filtered = current, bool(current)
        return self._filtered


def resolve(callback: Callable[..., Any], handle: int) -> _Item | None:
    """The monitored item behind the data-change ``callback`` registered under ``handle``, or None where
    :func:`notify` must call the callback itself: a callback that is not asyncua 2.1.0's
    ``MonitoredItemService.datachange_callback``, or a service without the tables this reads (another asyncua;
    decided at the service's first notification, :func:`_readable`). A handle the service does not know raises
    KeyError, as its callback would."""
    if getattr(callback, "__func__", None) is not MonitoredItemService.datachange_callback:
        return None   # not the service's callback: its own way
    service = callback.__self__
    readable = _READABLE.get(service)
    if readable is None:   # the service's first notification: decided once, not at each of its notifications
        readable = _READABLE[service] = _readable(service)
    if not readable:
        return None   # not the service this was written against (another asyncua): its own way
    mid = service._monitored_datachange[handle]
    return _Item(service._monitored_items[mid], mid, service.isub.enqueue_datachange_event)


def _notification(item: _Item, dv: ua.DataValue) -> ua.MonitoredItemNotification | None:
    """Make ``dv`` the item's current value (the one before its old) and answer its notification, or None: the item
    is disabled, or its change test (``_is_data_changed``, status or value, as asyncua's callback's for an item
    without a filter) says no change."""
    mdata = item.mdata
    if mdata.mode == _DISABLED:
        return None
    values = item.values
    if isinstance(dv, _SharedDataValue):   # never changed: its deep copy would be itself, at 2 µs
        values.old_dvalue, values.current_dvalue = values.current_dvalue, dv
    else:
        values.set_current_datavalue(dv)
    if _IS_DATA_CHANGED(values, _STATUS_VALUE):
        return ua.MonitoredItemNotification(ClientHandle=mdata.client_handle, Value=dv)
    return None


async def notify(callback: Callable[..., Any], handle: int, dv: ua.DataValue) -> None:
    """Hand ``dv`` to the monitored item behind the data-change ``callback`` registered under ``handle``: what
    asyncua 2.1.0's ``MonitoredItemService.datachange_callback`` does for an item without a filter, less one object.
    (The publisher's :meth:`OpcUaServer._hand` takes the same steps with each item resolved once per handle.)

    That callback builds ``ua.MonitoredItemNotification()`` with its default DataValue -- which builds a Variant
    whose type it guesses, and a StatusCode -- and then replaces that DataValue with the one it was handed: 13 µs
    in timeit on the 2-core machine at load 7, where a whole notification costs the OPC UA process about 50 µs idle
    (docs/benchmarks.md §9.8: 52-60 -> 32-45 µs per notification in the bench rows).
    Here the notification is built with the value (under 1 µs), through the same steps, the service's own:
    the item's mode, its current and old value (``set_current_datavalue``'s, without its deep copy of a value
    this server never changes, :class:`_SharedDataValue`: 2 µs more), its change test (``_is_data_changed``,
    status or value, as the callback's for an item without a filter) and its subscription's queue
    (``enqueue_datachange_event``, with the item's queue size). An item with a filter (a deadband), or a callback
    that is not that service's, goes through the callback itself; asyncua is not patched. Whether a service is
    the one this was written against is decided at its first notification (:func:`_readable`), not at each."""
    step = hand_over(resolve(callback, handle), callback, handle, dv)
    if step is not None:
        await step


def hand_over(item: _Item | None, callback: Callable[..., Any], handle: int,
              dv: ua.DataValue) -> Awaitable[Any] | None:
    """The one step that hands ``dv`` to the monitored item behind ``callback``'s ``handle`` (``item``, from
    :func:`resolve`), for :func:`notify` and the publisher's :meth:`OpcUaServer._hand` alike: the callback itself
    for an item it must take (None, or one with a filter), else the item's subscription queue's call with the
    notification (:func:`_notification`), or None where the item wants none. Returned to be awaited by the caller,
    so the publisher hands a value without a coroutine of its own per notification."""
    if item is None or item.filtered():
        return callback(handle, dv)
    event = _notification(item, dv)
    return None if event is None else item.enqueue(item.mid, event, item.mdata.queue_size)


class _SharedDataValue(ua.DataValue):
    """A DataValue this server makes fresh for every read and notification and never changes afterwards.

    asyncua deep-copies every value it hands to a monitored item (to guard against a caller changing it later);
    a deep copy of a DataValue costs about 0.3 ms, which made copying, not the process or the network, the
    cost of a subscription (10,000 notifications a second took 3 s of each second). Since nothing changes
    these values, a "copy" may be the value itself."""

    def __deepcopy__(self, memo: dict) -> _SharedDataValue:
        return self


_new = object.__new__
#: the fields of asyncua's Variant and DataValue that :func:`scalar_data_value` sets (asyncua 2.1.0's: all of them)
_VARIANT_FIELDS = ("Value", "VariantType", "Dimensions", "is_array")
_DATA_VALUE_FIELDS = ("Encoding", "Value", "StatusCode", "SourceTimestamp", "ServerTimestamp", "SourcePicoseconds",
                      "ServerPicoseconds")
#: whether asyncua's Variant and DataValue have exactly those fields (another asyncua: built by their constructors)
_BUILT_DIRECTLY = (tuple(f.name for f in fields(ua.Variant)) == _VARIANT_FIELDS
                   and tuple(f.name for f in fields(ua.DataValue)) == _DATA_VALUE_FIELDS)


def scalar_data_value(value: float | int | bool, variant: ua.VariantType, status: ua.StatusCode,
                      source_ts: datetime, server_ts: datetime) -> _SharedDataValue:
    """``_SharedDataValue(Value=ua.Variant(value, variant), StatusCode=status, SourceTimestamp=source_ts,
    ServerTimestamp=server_ts)`` for a scalar number or Boolean of a given built-in ``variant``: the same object,
    field by field, built without the constructors' checks, which for such a value change nothing (the Variant's
    ``__post_init__`` guesses a missing type, unwraps a Variant, refuses None and measures a list; the DataValue's
    wraps a value that is not a Variant): 1.24-1.44 -> 0.42-0.48 µs in timeit, once per sampled value. Where
    asyncua's classes have other fields than asyncua 2.1.0's, their constructors build it."""
    if not _BUILT_DIRECTLY:
        return _SharedDataValue(Value=ua.Variant(value, variant, None, False), StatusCode=status,
                                SourceTimestamp=source_ts, ServerTimestamp=server_ts)
    v = _new(ua.Variant)
    v.Value, v.VariantType, v.Dimensions, v.is_array = value, variant, None, False
    dv = _new(_SharedDataValue)
    dv.Encoding, dv.Value, dv.StatusCode, dv.SourceTimestamp, dv.ServerTimestamp = 0, v, status, source_ts, server_ts
    dv.SourcePicoseconds = dv.ServerPicoseconds = None
    return dv


class RepeatFilter(logging.Filter):
    """Let through at most one log record per logging call site every ``interval`` seconds.

    asyncua logs every malformed message a client sends with a full traceback; a client sending garbage as
    fast as it can would make formatting tracebacks the server's main work and starve the tick. Installed on
    asyncua's loggers while the server runs; the next record let through says how many were dropped."""

    def __init__(self, interval: float = 10.0) -> None:
        super().__init__()
        self.interval = interval
        self._last: dict[tuple[str, int], float] = {}
        self._dropped: dict[tuple[str, int], int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.pathname, record.lineno)   # the call site: asyncua formats values into some messages
        now = record.created
        if now - self._last.get(key, -math.inf) < self.interval:
            self._dropped[key] = self._dropped.get(key, 0) + 1
            return False
        self._last[key] = now
        dropped = self._dropped.pop(key, 0)
        if dropped:
            record.msg = f"{record.msg} ({dropped} more like this in the last {self.interval:g} s were not logged)"
        return True


def _asyncua_loggers() -> list[logging.Logger]:
    names = [n for n in logging.root.manager.loggerDict if n == "asyncua" or n.startswith("asyncua.")]
    return [logging.getLogger(n) for n in names]


async def _stop_clock_task(server: Server) -> None:
    """End asyncua's task that writes the server's CurrentTime once a second. ``Server.stop`` only flags it
    and waits for its one-second sleep to run out: every stop would take a second for nothing."""
    task, server.iserver.time_task = server.iserver.time_task, None
    if task is not None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


class _CheckedWrites(AttributeService):
    """asyncua's attribute service with the loop variables' writes routed through ``Device.write``."""

    def __init__(self, aspace: Any, adapter: OpcUaServer) -> None:
        super().__init__(aspace)
        self._adapter = adapter

    async def write(self, params: ua.WriteParameters, user: Any = None) -> list[ua.StatusCode]:
        results: list[ua.StatusCode] = []
        for item in params.NodesToWrite:
            target = self._adapter.targets.get(item.NodeId)
            if target is None:
                if item.NodeId in self._adapter.node_ids:   # our read-only nodes (bits, properties)
                    self._adapter.refused += 1
                    results.append(ua.StatusCode(ua.StatusCodes.BadNotWritable))
                else:
                    one = ua.WriteParameters(NodesToWrite=[item])
                    results.extend(await super().write(one, user) if user is not None else await super().write(one))
                continue
            if item.AttributeId != ua.AttributeIds.Value:
                self._adapter.refused += 1
                results.append(ua.StatusCode(ua.StatusCodes.BadNotWritable))
                continue
            results.append(await self._adapter.write(*target, item.Value, user))
        return results


class OpcUaServer:
    """Serve a device over OPC UA: ``async with OpcUaServer(device, loops=..., port=0) as srv``.

    Parameters
    ----------
    source : the device (:class:`~valve_emulator.opcua.source.DeviceSource`): ``LocalSource(device, station)``
        in this process, a ``RemoteSource`` in the OPC UA process; with a station, the station object has its
        methods (Freeze, Run, ...). A :class:`~valve_emulator.device.tick.Device` itself is served in this
        process without a station (``LocalSource(device)``).
    loops : the loop configs, in the device's order (names, PV units, PV range).
    host, port : where to listen (port 0: a free port, read back from :attr:`port`).
    security : :class:`OpcUaSecurity` (default: policy None, anonymous operators; loopback only).
    history : keep the last ``history`` seconds of every loop's PV, OP, SP and MV for HistoryRead
        (:mod:`~valve_emulator.opcua.history`), in SQLite at ``history_path`` (default in memory); None: none.
    publish_budget : the share of each tick period the publisher may spend feeding subscriptions before it
        defers the rest of a tick to the next (:data:`PUBLISH_BUDGET`; in a process of its own
        :data:`PROCESS_PUBLISH_BUDGET`, no limit: nothing deferred).
    yield_while_sampling : whether the publisher yields to the event loop every :data:`YIELD_EVERY` variables
        while it samples a tick (True, in the device's process: the tick and Modbus come first). False in a
        process of its own: a publish that ran in such a yield after the tick's hand-off was due would come before
        it (docs/benchmarks.md §9.6); sampling a tick there takes a few ms (2,000 variables: about 10 ms).
    hand_ahead : register each tick's hand-off on the grid :data:`HAND_AHEAD` ticks ahead and sample each chunk
        from the source when its timer fires (:meth:`_publish_ahead`; in a process of its own, where the source is
        the shared image the device writes whatever this process does). False: sample each tick when it arrives
        and hand it on the grid (:meth:`_publish`, in the device's process, with its budget).
    """

    def __init__(self, source: DeviceSource, *, loops: Sequence[Any], host: str = "127.0.0.1", port: int = 0,
                 security: OpcUaSecurity | None = None, history: float | None = None,
                 history_path: str = ":memory:", publish_budget: float = PUBLISH_BUDGET,
                 yield_while_sampling: bool = True, hand_ahead: bool = False) -> None:
        if isinstance(source, Device):
            source = LocalSource(source)
        self.source, self.loops, self.host, self.port = source, list(loops), host, int(port)
        #: each loop's byte offset in the register image, as Python ints (a numpy scalar's int(): 1 µs a value)
        self._starts = [int(offset) for offset in source.offsets]
        #: seconds of PV, OP, SP and MV kept for HistoryRead (None: no history), in SQLite at history_path
        self.history, self.history_path = history, history_path
        self.publish_budget, self.yield_while_sampling = publish_budget, yield_while_sampling
        self.hand_ahead = hand_ahead
        #: the source's snapshot the float32 variables were last decoded from, their columns by name (:meth:`_column`)
        self._decoded_from: TickImage | None = None
        self._columns: dict[str, list[float] | None] = {}
        #: the hand-off grid of :meth:`_publish_ahead`, the timers it registered (tick -> handles) and the chunks'
        #: tasks under way
        self._grid = HandOffGrid()
        self._slots: dict[int, list[asyncio.TimerHandle]] = {}
        self._handing: set[asyncio.Task] = set()
        #: the last tick whose hand-off began
        self._fired = -1
        #: the tick the last hand-off of :meth:`_publish_ahead` sampled, and its wall and process CPU time
        self._sampled = (0, math.nan, 0.0)
        self._historized: list[ua.NodeId] = []
        self.security = security or OpcUaSecurity()
        self.security.check(host)
        self.server: Server | None = None
        self.ns = 0
        #: NodeId -> (loop index, Variable) of every writable-or-not loop variable
        self.targets: dict[ua.NodeId, tuple[int, Variable]] = {}
        #: every node id this adapter created (for BadNotWritable on the others)
        self.node_ids: set[ua.NodeId] = set()
        self._monitored: list[tuple[Any, int, Sampler]] = []
        #: per group of monitored items (:class:`_Group`), by its key: the value last handed to it and when its next
        #: sample is due
        self._states: dict[tuple[int, float], _GroupState] = {}
        #: the seconds handing one variable's value to its monitored items takes (a running mean)
        self._hand_cost = 20e-6
        #: data-change callback handle -> its monitored item (:func:`resolve`; None: through the callback), resolved at
        #: its first notification; a deleted handle's is dropped with it
        self._resolved: dict[int, _Item | None] = {}
        #: data-change callback handle -> the sampling interval (s) its monitored item is honoured at
        self._intervals: dict[int, float] = {}
        #: when the tick that made the served values ran (their SourceTimestamp)
        self.tick_clock = TickClock(source)
        self._publisher: asyncio.Task | None = None
        self._log_filter = RepeatFilter()
        self._active: list[_Watch] = []
        self._samplers: dict[ua.NodeId, Sampler] = {}
        self._dirty = True
        #: data-change notifications handed to subscriptions (one per monitored item and change)
        self.notifications = 0
        #: ticks after which the publisher ran out of its budget and went on at the next tick
        self.deferred = 0
        #: ticks the publisher never sampled: a newer one had come by the time it was done with the one before
        self.skipped = 0
        #: the last ticks not handed on the grid (:class:`OffGrid`)
        self.off_grid: deque[OffGrid] = deque(maxlen=OFF_GRID_KEPT)
        #: hand-off chunks (:meth:`_hand_ahead`) that sampled a tick newer than their own, and those that sampled the
        #: tick that chunk of the hand-off before sampled (:class:`OpcUaCounters`); the tick each chunk last sampled
        self.sampled_newer = self.sampled_again = 0
        #: thread CPU seconds of the hand-off chunks of :meth:`_publish_ahead` (:class:`OpcUaCounters`)
        self.handing_cpu = 0.0
        self._chunk_ticks: dict[int, int] = {}
        self.writes = 0
        self.refused = 0
        #: refused writes and sessions, logged once per user (or client) and cause per interval
        self.refusals = RefusalLog(_log)
        #: the client certificates accepted (built at start from ``security.pki``/``trust_all``)
        self.trust_list: TrustList | None = None
        #: the loops' PV alarms as OPC UA conditions (:mod:`~valve_emulator.opcua.alarms`), once started
        self.alarm_conditions: AlarmConditions | None = None

    async def counters(self) -> OpcUaCounters:
        """What this server has done so far (async: the same call answers for a server in another process)."""
        trust = self.trust_list
        conditions = self.alarm_conditions
        return OpcUaCounters(notifications=self.notifications, deferred=self.deferred, skipped=self.skipped,
                             writes=self.writes,
                             refused=self.refused, trust_accepted=trust.accepted if trust else 0,
                             trust_refused=trust.refused if trust else 0,
                             alarm_events=conditions.sent if conditions else 0, off_grid=tuple(self.off_grid),
                             sampled_newer=self.sampled_newer, sampled_again=self.sampled_again,
                             handing_cpu=self.handing_cpu)

    # --- values -----------------------------------------------------------------------------------------

    def _words(self, index: int, reg: Register) -> Sequence[int]:
        start = self._starts[index] + 2 * reg.address
        raw = self.source.image[start:start + 2 * reg.width]
        return [int.from_bytes(raw[k:k + 2], "big") for k in range(0, len(raw), 2)]

    def value(self, index: int, var: Variable) -> float | int:
        """The variable's value now, in engineering units: the register image's (so a write shows at once), as
        the double the tick computed where the image holds it as float32 (see :meth:`_double`)."""
        if var.read.type is DataType.FLOAT32:   # what a subscription samples most: straight from the image's bytes
            column = self._column(var)
            if column is not None:   # decoded for every loop at once (the OPC UA process: once per tick)
                return column[index]
            source = self.source
            start = self._starts[index] + 2 * var.read.address
            high, low = _WORDS.unpack_from(source.image, start)
            if source.scaling.word_order is CDAB:
                high, low = low, high
            return self._double(index, var, _FLOAT32.unpack(_WORDS.pack(high, low))[0])
        words = self._words(index, var.read)
        if var.read.width == 2:   # a counter, in the device's word order (float32 was read above)
            return int(from_words(words, var.read.type, self.source.scaling.word_order))
        raw = words[0] - 65536 if var.read.type is DataType.INT16 and words[0] >= 32768 else words[0]
        value = decode_value(var.read, raw, self.source.scaling, index)
        if var.analog:
            return float(value) if math.isfinite(value) else 0.0
        return int(value)

    def _double(self, index: int, var: Variable, image: float) -> float:
        """A float32 register's value as a double without float32 artefacts (``time`` 1.3, not 1.2999999523).

        The tick encodes the bank's doubles as float32; where the bank's double still encodes to the image's
        float32 it is the value, at full precision. Where they differ a write has changed the image since the
        tick: then the shortest decimal that reads back as that float32 (the written 61.3, not 61.29999924)."""
        computed = self.source.computed(index, var.first.quantity)
        if computed is not None:
            try:
                if _FLOAT32.unpack(_FLOAT32.pack(computed))[0] == image:   # (a float32 read back is exact)
                    return computed
            except OverflowError:   # beyond the largest float32: numpy rounds it to infinity
                if np.float32(computed) == np.float32(image):
                    return computed
        return float(str(np.float32(image)))

    def _column(self, var: Variable) -> list[float] | None:
        """The float32 variable ``var``'s doubles on every loop, as :meth:`value` serves each, decoded at once from the
        source's :attr:`~valve_emulator.opcua.source.DeviceSource.snapshot` and kept while it is the one served (the
        OPC UA process: once per tick, where each value decoded alone cost 2 µs of every notification); None without
        a snapshot (in the device's process, where the image changes in place) or for a quantity without doubles
        (``time``, the tuning)."""
        source = self.source
        snapshot = source.snapshot
        if snapshot is None:
            return None
        if snapshot is not self._decoded_from:
            self._decoded_from, self._columns = snapshot, {}
        columns = self._columns
        if var.name in columns:
            return columns[var.name]
        computed = source.computed_column(snapshot, var.first.quantity)
        column = columns[var.name] = None if computed is None else self._doubles(var, snapshot.image, computed)
        return column

    def _doubles(self, var: Variable, image: bytes, computed: np.ndarray) -> list[float]:
        """:meth:`_double` of every loop at once: float32 register ``var.read`` of every loop in ``image``, each the
        loop's ``computed`` double where that still encodes to the image's float32, else the shortest decimal that
        reads back as it."""
        order = (2, 3, 0, 1) if self.source.scaling.word_order is CDAB else (0, 1, 2, 3)
        at = np.asarray(self._starts, dtype=np.intp)[:, None] + (2 * var.read.address + np.asarray(order))
        floats = np.frombuffer(image, dtype=np.uint8)[at].view(">f4").ravel()
        with np.errstate(over="ignore", invalid="ignore"):   # beyond the largest float32: infinity, as _double's
            same = computed.astype(np.float32) == floats
        column = computed.tolist()
        for k in np.flatnonzero(~same).tolist():   # a write since the tick (or NaN): as _double answers it
            column[k] = float(str(np.float32(floats[k])))
        return column

    def _data_value(self, value: Any, variant: ua.VariantType, status: ua.StatusCode | None = None,
                    stamps: tuple[datetime, datetime] | None = None) -> ua.DataValue:
        """The DataValue of a read or a notification: SourceTimestamp the tick that made the value, ServerTimestamp
        now; ``stamps``: the two, taken once for a publisher's pass over a tick's values (sampled together)."""
        source_ts, server_ts = stamps or (self.tick_clock.stamp(), datetime.now(UTC))
        return scalar_data_value(value, variant, status or _GOOD, source_ts, server_ts)

    def _sampler(self, index: int, var: Variable, eu_range: tuple[float, float] | None) -> Sampler:
        """The sampler of an analog or integer variable; a value outside ``eu_range`` is Uncertain."""
        variant = var.variant
        if eu_range is None:
            return lambda: (self.value(index, var), variant, None)
        lo, hi = eu_range

        def sample() -> tuple[Any, ua.VariantType, ua.StatusCode | None]:
            value = self.value(index, var)
            return value, variant, None if lo <= value <= hi else _EU_EXCEEDED

        return sample

    def _bit_sampler(self, index: int, bit: Status) -> Sampler:
        return lambda: (bool(int(self.value(index, _STATUS)) & int(bit)), ua.VariantType.Boolean, None)

    def _reader(self, sampler: Sampler) -> Callable[..., ua.DataValue]:
        """What asyncua calls to read a variable: its sample now, as a DataValue."""
        return lambda *_: self._data_value(*sampler())

    # --- writes ---------------------------------------------------------------------------------------

    async def write(self, index: int, var: Variable, dv: ua.DataValue, user: Any) -> ua.StatusCode:
        """One client write of ``var`` on loop ``index`` through ``Device.write``; the OPC UA status code."""
        if var.write is None:
            self.refused += 1
            return ua.StatusCode(ua.StatusCodes.BadNotWritable)
        value = dv.Value.Value if dv.Value is not None else None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.refused += 1
            return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
        role = user.station_role if isinstance(user, StationUser) else OPERATOR
        if not role.may_write(var.write.quantity):
            self._refused_write(user, role, index, var)
            return ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
        try:
            words = encode_write(var.write, value, self.source.scaling, index)
            await self.source.write(index, var.write.address, words, role)
        except RegisterValueError:
            self.refused += 1
            return ua.StatusCode(ua.StatusCodes.BadOutOfRange)
        except RegisterAccessError:
            self.refused += 1
            return ua.StatusCode(ua.StatusCodes.BadNotWritable)
        except RegisterError:
            self.refused += 1
            return ua.StatusCode(ua.StatusCodes.BadNotWritable)
        self.writes += 1
        return ua.StatusCode()

    def _refused_write(self, user: Any, role: Role, index: int, var: Variable) -> None:
        """Count and log (once per user and variable per interval) a write the user's role may not make."""
        self.refused += 1
        name = getattr(user, "name", None) or "anonymous"
        self.refusals.note(name, (var.name, role.name), "refused OPC UA write of %s.%s by user %r (role %r): "
                           "BadUserAccessDenied, the role does not write %s", self.loops[index].name, var.name,
                           name, role.name, var.name)

    # --- address space --------------------------------------------------------------------------------

    def _node_id(self, identifier: str) -> ua.NodeId:
        return ua.NodeId(identifier, self.ns)

    def _object_item(self, parent: ua.NodeId, identifier: str, name: str,
                     typedef: ua.NodeId | int = ua.ObjectIds.BaseObjectType) -> ua.AddNodesItem:
        """An object under ``parent`` typed ``typedef``; a type's children are not copied (each loop gets its
        own variables, with its own ranges and units)."""
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = self._node_id(identifier)
        item.BrowseName = ua.QualifiedName(name, self.ns)
        item.NodeClass = ua.NodeClass.Object
        item.ParentNodeId = parent
        folder = parent == ua.NodeId(ua.ObjectIds.ObjectsFolder)
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.Organizes if folder else ua.ObjectIds.HasComponent)
        item.TypeDefinition = typedef if isinstance(typedef, ua.NodeId) else ua.NodeId(typedef)
        attrs = ua.ObjectAttributes()
        attrs.DisplayName = attrs.Description = ua.LocalizedText(name)
        item.NodeAttributes = attrs
        return item

    def _variable_item(self, parent: ua.NodeId, name: str, value: Any, variant: ua.VariantType, typedef: int, *,
                       writable: bool = False, datatype: int | None = None, prop: bool = False,
                       historizing: bool = False) -> ua.AddNodesItem:
        """A variable (or, ``prop``, a property) ``name`` of ``parent``; node id ``<parent id>.<name>``;
        ``historizing``: its history may be read (HistoryRead)."""
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = self._node_id(f"{parent.Identifier}.{name}")
        item.BrowseName = ua.QualifiedName(name, 0 if prop else self.ns)
        item.NodeClass = ua.NodeClass.Variable
        item.ParentNodeId = parent
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasProperty if prop else ua.ObjectIds.HasComponent)
        item.TypeDefinition = ua.NodeId(ua.ObjectIds.PropertyType if prop else typedef)
        attrs = ua.VariableAttributes()
        attrs.DisplayName = attrs.Description = ua.LocalizedText(name)
        attrs.DataType = ua.NodeId(datatype if datatype is not None else int(variant.value))
        attrs.Value = ua.Variant(value, variant)
        attrs.ValueRank = ua.ValueRank.Scalar
        access = ua.AccessLevel.CurrentRead.mask | (ua.AccessLevel.CurrentWrite.mask if writable else 0)
        if historizing:
            access |= ua.AccessLevel.HistoryRead.mask
            attrs.Historizing = True
        attrs.AccessLevel = attrs.UserAccessLevel = access
        item.NodeAttributes = attrs
        return item

    async def _add(self, items: list[ua.AddNodesItem]) -> None:
        """Add ``items`` to the address space, in order, in batches."""
        session = self.server.iserver.isession
        for k in range(0, len(items), 5000):
            for result in await session.add_nodes(items[k:k + 5000]):
                result.StatusCode.check()
                self.node_ids.add(result.AddedNodeId)

    @staticmethod
    def _eu_range(loop: Any, var: Variable) -> tuple[float, float] | None:
        """The EURange: ``plant.pv_range`` for PV and SP, 0 .. its span for a width in PV units (noise), the
        register's range for a % travel / % flow quantity; None for the others (tuning, time)."""
        lo, hi = map(float, loop.plant.pv_range)
        if var.first.conversion is Conversion.PV_SPAN:
            return 0.0, hi - lo
        if var.units == PV_UNITS:
            return lo, hi
        return var.percent_range

    @staticmethod
    def _units(loop: Any, var: Variable) -> str:
        """The variable's unit text: the loop's PV units in place of "PV units" ("% per PV unit" for kc)."""
        pv_units = str(loop.plant.units).strip()
        if var.units == PV_UNITS:
            return pv_units
        return var.units.replace("PV unit", pv_units) if pv_units else var.units

    @staticmethod
    def _typedef(var: Variable) -> int:
        return ua.ObjectIds.AnalogItemType if var.analog else ua.ObjectIds.BaseDataVariableType

    async def _define_loop_type(self) -> ua.NodeId:
        """LoopType under BaseObjectType: the variables every loop object has (modelling rule Mandatory)."""
        base = self.server.get_node(ua.ObjectIds.BaseObjectType)
        loop_type = await base.add_object_type(self._node_id("LoopType"), ua.QualifiedName("LoopType", self.ns))
        items = [self._variable_item(loop_type.nodeid, v.name, 0.0 if v.analog else 0, v.variant, self._typedef(v),
                                     writable=v.write is not None) for v in VARIABLES]
        items += [self._variable_item(loop_type.nodeid, name, False, ua.VariantType.Boolean,
                                      ua.ObjectIds.TwoStateDiscreteType) for name in BITS]
        await self._add(items)
        for item in items:
            await self.server.get_node(item.RequestedNewNodeId).set_modelling_rule(True)
        return loop_type.nodeid

    def _loop_items(self, unit: ua.NodeId, index: int, loop: Any, loop_type: ua.NodeId) -> list[ua.AddNodesItem]:
        """The object of loop ``index`` under its unit, its variables and their properties."""
        name = str(loop.name)
        obj = self._object_item(unit, f"{unit.Identifier}.{name}", name, loop_type)
        items = [obj]
        for var in VARIABLES:
            historizing = self.history is not None and var.name in HISTORIZED
            node = self._variable_item(obj.RequestedNewNodeId, var.name, self.value(index, var), var.variant,
                                       self._typedef(var), writable=var.write is not None, historizing=historizing)
            items.append(node)
            if historizing:
                self._historized.append(node.RequestedNewNodeId)
            self.targets[node.RequestedNewNodeId] = (index, var)
            self._samplers[node.RequestedNewNodeId] = self._sampler(index, var, self._eu_range(loop, var)
                                                                    if var.analog else None)
            if var.analog:
                items += self._analog_properties(node.RequestedNewNodeId, loop, var)
        for bit_name, (bit, true_state, false_state) in BITS.items():
            node = self._variable_item(obj.RequestedNewNodeId, bit_name, False, ua.VariantType.Boolean,
                                       ua.ObjectIds.TwoStateDiscreteType)
            items.append(node)
            self._samplers[node.RequestedNewNodeId] = self._bit_sampler(index, bit)
            for prop, text in (("TrueState", true_state), ("FalseState", false_state)):
                items.append(self._variable_item(node.RequestedNewNodeId, prop, ua.LocalizedText(text),
                                                 ua.VariantType.LocalizedText, 0, prop=True))
        return items

    def _analog_properties(self, node: ua.NodeId, loop: Any, var: Variable) -> list[ua.AddNodesItem]:
        """EURange (where the variable has one) and EngineeringUnits (where it has units) of an analog item."""
        items = []
        rng = self._eu_range(loop, var)
        if rng is not None:
            items.append(self._variable_item(node, "EURange", ua.Range(Low=rng[0], High=rng[1]),
                                             ua.VariantType.ExtensionObject, 0, datatype=ua.ObjectIds.Range,
                                             prop=True))
        eu = eu_information(self._units(loop, var), own_namespace=NAMESPACE)
        if eu is not None:
            items.append(self._variable_item(node, "EngineeringUnits", eu, ua.VariantType.ExtensionObject, 0,
                                             datatype=ua.ObjectIds.EUInformation, prop=True))
        return items

    def _serve_values(self) -> None:
        """Answer reads of the loop variables from the register image, and watch them for subscriptions."""
        aspace = self.server.iserver.aspace
        for node_id, sampler in self._samplers.items():
            aspace.set_attribute_value_callback(node_id, ua.AttributeIds.Value, self._reader(sampler))
            attval = aspace._nodes[node_id].attributes[ua.AttributeIds.Value]
            self._monitored.append((attval, len(self._monitored), sampler))

    async def _add_methods(self, station_node: Any) -> None:
        if not self.source.has_station:
            return
        methods = (
            ("Freeze", self._freeze, [], []),
            ("Run", self._run, [], []),
            ("SetSpeed", self._set_speed, [ua.VariantType.Double], []),
            ("Snapshot", self._snapshot, [ua.VariantType.String], [ua.VariantType.String]),
            ("Restore", self._restore, [ua.VariantType.String], [ua.VariantType.String]),
            ("InjectMalfunction", self._inject, [ua.VariantType.String], [ua.VariantType.String]),
        )
        for name, func, inputs, outputs in methods:
            node = await station_node.add_method(ua.NodeId(f"ValveEmulator.{name}", self.ns),
                                                 ua.QualifiedName(name, self.ns), func, inputs, outputs)
            self.node_ids.add(node.nodeid)

    # --- the station's methods (instructors only: RoleRuleset refuses calls of operators) --------------

    async def _guarded(self, action: str, argument: Any = None) -> list[ua.Variant] | ua.StatusCode:
        """Run a station action; its refusal (:class:`~valve_emulator.opcua.source.StationRefusal`) becomes
        BadNotFound (an unknown snapshot) or BadInvalidArgument, and a result is handed back as JSON text."""
        try:
            result = await self.source.station_action(action, argument)
        except StationRefusal as exc:
            _log.info("OPC UA: station method refused: %s", exc.args[0])
            code = ua.StatusCodes.BadNotFound if exc.status == 404 else ua.StatusCodes.BadInvalidArgument
            return ua.StatusCode(code)   # asyncua answers a raised error as BadUnexpectedError
        return [] if result is None else [ua.Variant(json.dumps(result), ua.VariantType.String)]

    async def _freeze(self, parent: Any) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded("freeze")

    async def _run(self, parent: Any) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded("run")

    async def _set_speed(self, parent: Any, time_scale: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded("speed", time_scale.Value)

    async def _snapshot(self, parent: Any, name: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded("snapshot", name.Value)

    async def _restore(self, parent: Any, name: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded("restore", name.Value)

    async def _inject(self, parent: Any, body: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        try:
            parsed = json.loads(body.Value)
        except (TypeError, ValueError):
            return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)
        return await self._guarded("malfunction", parsed)

    # --- publishing ------------------------------------------------------------------------------------

    async def _publish(self) -> None:
        """After every tick, hand each group of monitored items whose sample is due the variable's value, when it
        changed since the group last got it.

        Only variables with a monitored item are read (the list is rebuilt when a client adds or deletes
        one), and only when one of their groups is due: an item sampled at 1 s is handed one value a second, the
        tick's latest, however fast the tick (a due time counts from half a tick early, so tick jitter does not
        skip a sample; the variables' phases are spread over the interval, :func:`first_due`).

        The values are sampled when the tick arrives and handed at once when the hand-off is due, on a grid of the
        tick period (:mod:`~valve_emulator.opcua.handoff`): so each publishing interval of a subscription holds
        exactly one tick's values, whatever the tick's jitter and the subscription's phase. The tick comes first:
        sampling yields to the event loop every :data:`YIELD_EVERY` variables (in the device's process:
        ``yield_while_sampling``), and there, once sampling and the hand-off would take more than the publisher's
        share of the tick period (:data:`PUBLISH_BUDGET`), it stops and goes on after the next tick where it
        stopped, so a subscription larger than the machine can feed gets every variable's latest value less often
        instead of delaying the tick. In a process of its own nothing is deferred (:data:`PROCESS_PUBLISH_BUDGET`):
        a tick's due values are all handed at its hand-off, into the publishing interval they belong to; a
        publisher behind the device takes the newest tick once it is done with the last, or, if that tick's
        hand-off is past by half a tick or more (``TAKE_LATE``), the next one (the ticks it never sampled counted in
        :attr:`skipped`). (The OPC UA process hands ahead instead: :meth:`_publish_ahead`.)"""
        source, seen, at = self.source, self.source.ticks, 0
        loop = asyncio.get_running_loop()
        grid = HandOffGrid()
        last = (loop.time(), time.process_time())   # the last tick's arrival: wall and process CPU time
        while True:
            previous, newest = seen, source.ticks
            done = loop.time()
            if newest > seen and grid.overdue(newest, done, source.period):
                seen = newest   # came while the last pass ran, its hand-off already past: wait for a fresh one
            seen = await source.wait_for_tick(seen + 1)
            arrived, cpu = loop.time(), time.process_time()
            stamp = self.tick_clock.stamp().timestamp()   # the tick just ran: its time is now
            if self._dirty:
                self._dirty, at = False, 0
                self._active = self._watches()
            period = finite_period(source)
            on_grid = grid.on_grid
            due = grid.due(seen, arrived, source.period)
            self._note_off_grid(previous, seen, stamp, period, done - on_grid, arrived > grid.on_grid,
                                arrived - grid.on_grid, (cpu - last[1]) / max(arrived - last[0], 1e-9))
            last = (arrived, cpu)
            chunks = -(-len(self._active) // HAND_CHUNK)
            sampled_at = grid.on_grid if math.isfinite(grid.on_grid) else due
            with Wakeups(chunk_times(due, period, chunks, HAND_SPACING)) as wakeups:
                handing, at = await self._sample(at, sampled_at, period, self.publish_budget * period)
                await self._hand_all(handing, wakeups)

    async def _publish_ahead(self) -> None:
        """The publisher of a process of its own: each tick's hand-off registered on the grid :data:`HAND_AHEAD`
        ticks ahead, each chunk sampling its due groups from the source when its timer fires.

        asyncua's publish timers and the hand-off's share the event loop's heap and run in the order of their due
        times however late the loop runs (:class:`~valve_emulator.opcua.handoff.Wakeups`). :meth:`_publish` puts a
        tick's hand-off there only when the tick's note is read and its pass begins -- after the pass before is
        done -- so a loop held past a hand-off let the publishes due meanwhile run before it, without the values
        due there (docs/benchmarks.md §9.16). Here the hand-offs of the next ticks are on the heap before the loop
        is held: when it runs again each comes before every publish due after it, and each samples its own tick
        from the shared image, which keeps the device's last ``shared.SLOTS`` ticks (its SourceTimestamp that
        tick's; the newest when it is older than those), so every publish holds one value of each item due since
        the one before, whatever the loop's lateness. (Sampling the newest tick, a hand-off run after the device
        published the next one took that tick from the next hand-off, which then handed its every-tick items
        nothing: docs/benchmarks.md §9.19.) Each registered hand-off, when
        its first chunk fires, registers the one :data:`HAND_AHEAD` ticks after it.

        This loop only keeps the grid: it reads each tick's note for the time the device ran the tick (the image's,
        not the note's arrival, which is late when this process was) and registers the hand-offs anew when the grid
        moves (``HandOffGrid``: a resume, a restored snapshot, a new period). Without a real-time period (lockstep,
        time frozen) each tick is sampled and handed when it arrives, at once."""
        source, loop = self.source, asyncio.get_running_loop()
        grid, seen = self._grid, source.ticks
        try:
            while True:
                seen = await source.wait_for_tick(seen + 1)
                period = source.period
                if not (math.isfinite(period) and period > 0):
                    self._cancel_slots()
                    self._refresh()
                    await self._hand(self._hand_ahead(seen, loop.time(), 0, 1, finite_period(source)))
                    continue
                with source.sampling():   # the newest tick and its time, from one copy of the image
                    seen, ran = max(seen, source.ticks), source.tick_time
                arrived = loop.time() if ran is None else loop.time() - max(0.0, time.time() - ran)
                anchors = grid.anchors
                due = grid.due(seen, arrived, period)
                if grid.anchors != anchors:   # the grid moved: the hand-offs ahead anew
                    self._cancel_slots()
                    self._fired = min(self._fired, seen - 1)
                # the hand-offs ahead kept registered: each registers the one HAND_AHEAD after it, but not once its
                # time is past (a hold longer than them, a resume before the grid moved), and then these do
                for tick in range(seen, seen + HAND_AHEAD):
                    self._register(tick)
                if seen > self._fired and seen not in self._slots:   # its time long past: handed at once, late
                    self._fire(seen, due, 0, 1)
        finally:
            self._cancel_slots()
            for task in list(self._handing):
                task.cancel()

    def _register(self, tick: int) -> None:
        """Put tick number ``tick``'s hand-off chunks on the event loop's timer heap at their times on the grid."""
        grid, loop = self._grid, asyncio.get_running_loop()
        when, period = grid.at(tick), grid.period
        if tick in self._slots or tick <= self._fired or not math.isfinite(when) or when < loop.time() - period:
            return   # registered or handed, no grid, or past by a tick or more (a hold, a resume before the grid moved)
        chunks = max(1, -(-len(self._active) // HAND_CHUNK))
        self._slots[tick] = [loop.call_at(at, self._fire, tick, when, k, chunks)
                             for k, at in enumerate(chunk_times(when, period, chunks, HAND_SPACING))]

    def _cancel_slots(self) -> None:
        for handles in self._slots.values():
            for handle in handles:
                handle.cancel()
        self._slots.clear()

    def _fire(self, tick: int, when: float, chunk: int, chunks: int) -> None:
        """A registered chunk's timer: its hand-off in a task of its own, which the event loop runs in the order of
        the timers (a publish woken by an earlier timer before it, one woken by a later timer after it)."""
        task = asyncio.get_running_loop().create_task(self._hand_timed(tick, when, chunk, chunks))
        self._handing.add(task)
        task.add_done_callback(self._handing.discard)

    async def _hand_timed(self, tick: int, when: float, chunk: int, chunks: int) -> None:
        if chunk == 0:
            self._fired = max(self._fired, tick)
            for old in [t for t in self._slots if t < tick]:   # fired (or never to fire: the grid moved on)
                for handle in self._slots.pop(old):
                    handle.cancel()
            if self._refresh():   # the monitored variables changed: register the hand-offs ahead in as many chunks
                for ahead in [t for t in self._slots if t > tick]:
                    for handle in self._slots.pop(ahead):
                        handle.cancel()
                for ahead in range(tick + 1, tick + HAND_AHEAD):
                    self._register(ahead)
            self._register(tick + HAND_AHEAD)
        cpu = time.thread_time()
        try:
            await self._hand(self._hand_ahead(tick, when, chunk, chunks, self._grid.period))
        finally:
            self.handing_cpu += time.thread_time() - cpu

    def _refresh(self) -> bool:
        """Rebuild the list of monitored variables if a client changed it; whether it was rebuilt."""
        if not self._dirty:
            return False
        self._dirty = False
        self._active = self._watches()
        return True

    def _hand_ahead(self, tick: int, when: float, chunk: int, chunks: int,
                    period: float) -> list[tuple[int, _Watch, ua.DataValue, list[_Group]]]:
        """The values chunk ``chunk`` of ``chunks`` of tick ``tick``'s hand-off (due on the grid at ``when``) hands:
        of the variables at its places (the last chunk: to the end of the list) whose groups are due at ``when``,
        sampled from tick ``tick`` of the source, or the newest before it the source still keeps
        (``source.sampling(tick)``: never half of one tick and half of the next), stamped with that tick's time. The
        first chunk keeps the ticks no hand-off sampled and a hand-off run late (``OffGrid``)."""
        active, slack = self._active, period / 2
        low, high = chunk * HAND_CHUNK, len(active) if chunk == chunks - 1 else (chunk + 1) * HAND_CHUNK
        handing = []
        with self.source.sampling(tick):
            if chunk == 0:
                self._note_sampled(tick, when, period)
            sampled = self.source.ticks
            self.sampled_newer += sampled > tick
            self.sampled_again += self._chunk_ticks.get(chunk) == sampled
            self._chunk_ticks[chunk] = sampled
            if low >= len(active):
                return handing
            stamps = (self.tick_clock.stamp(), datetime.now(UTC))
            for place in range(low, min(high, len(active))):
                watch = active[place]
                if when < watch.soonest - slack:   # none of its groups due: not even a call
                    continue
                changed = self._changed(watch, when, slack, stamps)
                if changed:
                    handing.append((place, watch, *changed))
        return handing

    def _note_sampled(self, tick: int, when: float, period: float) -> None:
        """Count and keep the ticks between the last hand-off's and this one's (tick ``tick``'s, due at ``when``)
        that none sampled (``skipped``) and this hand-off when it runs :data:`HANDED_LATE` of a period after
        ``when`` (:class:`OffGrid`)."""
        loop = asyncio.get_running_loop()
        now, cpu, sampled = loop.time(), time.process_time(), self.source.ticks
        last, last_wall, last_cpu = self._sampled
        if sampled < last:   # a restored snapshot
            last = sampled
        busy = (cpu - last_cpu) / max(now - last_wall, 1e-9) if math.isfinite(last_wall) else 0.0
        late = now - when
        if sampled > last + 1 and last:
            stamp = self.tick_clock.stamp().timestamp()
            self.skipped += sampled - last - 1
            self.off_grid.extend(OffGrid(k, stamp - (sampled - k) * period, True, late - (tick - k) * period,
                                         busy) for k in range(last + 1, sampled))
        if late > HANDED_LATE * period:
            self.off_grid.append(OffGrid(sampled, self.tick_clock.stamp().timestamp(), False, late, busy))
        self._sampled = (max(sampled, last), now, cpu)

    def _note_off_grid(self, previous: int, seen: int, stamp: float, period: float, done_late: float,
                       handed_late: bool, late: float, busy: float) -> None:
        """Count and keep (:attr:`off_grid`) the ticks between ``previous`` and ``seen`` the publisher skipped (it
        was done with ``previous`` ``done_late`` seconds after that tick's hand-off on the grid) and tick ``seen``
        when it is handed ``late`` seconds after its hand-off on the grid (``handed_late``); ``stamp``: ``seen``'s
        time (POSIX seconds), ``busy``: the process's CPU share since the tick before (:class:`OffGrid`)."""
        if seen > previous + 1:
            self.skipped += seen - previous - 1
            self.off_grid.extend(OffGrid(k, stamp - (seen - k) * period, True, done_late - (k - previous) * period,
                                         busy) for k in range(previous + 1, seen))
        if handed_late:
            self.off_grid.append(OffGrid(seen, stamp, False, late, busy))

    async def _sample(self, at: int, due: float, period: float,
                      budget: float) -> tuple[list[tuple[int, _Watch, ua.DataValue, list[_Group]]], int]:
        """The values to hand at ``due``: of each monitored variable from the ``at``-th on whose groups are due
        then and changed (:meth:`_changed`), each with its place in the list of monitored variables, and where the
        next tick goes on: past the last variable sampled when
        sampling and the hand-off would take more than ``budget`` seconds (counted in :attr:`deferred`). ``due`` is
        the tick's hand-off time on the grid (``HandOffGrid.on_grid``), also for a tick handed late: which tick
        takes an item's sample does not depend on the ticks' lateness.

        Sampling that is not done by ``due`` (half a tick after the tick: a machine too busy for the subscriptions)
        makes the hand-off late, and a publish due between the two sees this tick's values of its items one
        interval early; the values stay this tick's, and the next hand-off is on the grid again."""
        active, handing, done = self._active, [], 0
        clock = asyncio.get_running_loop().time
        start = clock()
        slack = period / 2
        stamps = (self.tick_clock.stamp(), datetime.now(UTC))   # one sample of the tick: one pair of timestamps
        while done < len(active):
            if done and done % YIELD_EVERY == 0:
                if self.yield_while_sampling:
                    await asyncio.sleep(0)
                if budget < math.inf and clock() - start + len(handing) * self._hand_cost > budget:
                    self.deferred += 1
                    break
            place, watch = at, active[at]
            at, done = (at + 1) % len(active), done + 1
            if due < watch.soonest - slack:   # none of its groups due: not even a call
                continue
            changed = self._changed(watch, due, slack, stamps)
            if changed:
                handing.append((place, watch, *changed))
        return handing, at

    async def _hand_all(self, handing: list[tuple[int, _Watch, ua.DataValue, list[_Group]]],
                        wakeups: Wakeups) -> None:
        """Hand the sampled values in chunks: the variables at places ``k·HAND_CHUNK`` to ``(k+1)·HAND_CHUNK``
        in the list of monitored variables at the ``k``-th of ``wakeups``
        (:func:`~valve_emulator.opcua.handoff.chunk_times`), each chunk in a task of its own and without yielding
        (a publish woken meanwhile would come between two of its items). The chunks' times were all put on the
        event loop's timer heap when the tick arrived, so a publish due before a chunk's time comes before it and
        one due after it after, however late the loop runs (:class:`~valve_emulator.opcua.handoff.Wakeups`). A
        variable keeps its chunk's time from tick to tick, so a publish comes before or after it the same way at
        every tick, and waits for one chunk at most, not for the whole hand-off (its client's next Publish request
        has that much less time to come). Keeps the cost per variable for the budget."""
        if not handing:
            return
        clock = asyncio.get_running_loop().time
        spent = [0.0]

        async def hand_chunk(chunk: int, items: list[tuple[int, _Watch, ua.DataValue, list[_Group]]]) -> None:
            await wakeups.wait(chunk)
            start = clock()
            await self._hand(items)
            spent[0] += clock() - start

        await asyncio.gather(*(hand_chunk(chunk, list(items)) for chunk, items
                               in itertools.groupby(handing, key=lambda item: item[0] // HAND_CHUNK)))
        self._hand_cost += 0.2 * (spent[0] / len(handing) - self._hand_cost)

    def _changed(self, watch: _Watch, now: float, slack: float,
                 stamps: tuple[datetime, datetime]) -> tuple[ua.DataValue, list[_Group]] | None:
        """The value of ``watch`` and its groups due at ``now`` (``slack`` seconds early counts) that have not had
        it yet (their due times and last values moved on), or None: most variables on most ticks, which then cost
        no coroutine. ``stamps``: the pass's SourceTimestamp and ServerTimestamp."""
        sampled = None
        groups = []
        soonest = math.inf
        for group in watch.groups:
            state = group.state
            due = state.due
            if due is None:
                due = state.due = first_due(now, group.interval, group.key[0])
            if now < due - slack:
                if due < soonest:
                    soonest = due
                continue
            due = state.due = next_due(due, now, group.interval)
            if due < soonest:
                soonest = due
            if sampled is None:
                sampled = watch.sample()
            if state.sent == sampled[0]:   # unchanged: no DataValue made
                continue
            state.sent = sampled[0]
            groups.append(group)
        watch.soonest = soonest
        return (self._data_value(*sampled, stamps), groups) if groups else None

    async def _hand(self, items: list[tuple[int, _Watch, ua.DataValue, list[_Group]]]) -> None:
        """Hand each of ``items`` (place, variable, value, groups) to the monitored items of its groups, in order and
        without yielding between them (one coroutine for them all, not one per variable), as :func:`notify` hands a
        value, each item resolved once per handle (:attr:`_resolved`) rather than at each notification."""
        handed = 0
        resolved = self._resolved
        try:
            for _, watch, dv, groups in items:
                callbacks = watch.attval.datachange_callbacks
                for group in groups:
                    for handle in group.handles:
                        callback = callbacks.get(handle)
                        if callback is None:   # deleted since the list was built
                            continue
                        handed += 1
                        try:
                            item = resolved.get(handle, _UNRESOLVED)
                            if item is _UNRESOLVED:
                                item = resolved[handle] = resolve(callback, handle)
                            step = hand_over(item, callback, handle, dv)
                            if step is not None:
                                await step
                        except Exception:   # one broken subscription must not stop the others
                            _log.exception("OPC UA: a data-change notification failed")
        finally:
            self.notifications += handed

    def _watches(self) -> list[_Watch]:
        """The monitored variables, their items grouped by sampling interval; each group keeps its state (due time,
        last value) under its key, and the states of groups that no longer exist are forgotten."""
        watches = []
        states = {}
        for attval, key, sample in self._monitored:
            by_interval: dict[float, list[int]] = {}
            for handle in attval.datachange_callbacks:
                by_interval.setdefault(self._intervals.get(handle, 0.0), []).append(handle)
            if by_interval:
                groups = []
                for interval, handles in sorted(by_interval.items()):
                    group_key = (key, interval)
                    state = states[group_key] = self._states.get(group_key) or _GroupState()
                    groups.append(_Group(group_key, interval, tuple(handles), state))
                watches.append(_Watch(attval, sample, tuple(groups)))
        self._states = states
        return watches

    def _sampling_requested(self, event: Any, _dispatcher: Any) -> None:
        """Note the sampling interval of each monitored item a client created or modified (asyncua's
        ItemSubscriptionCreated/Modified server callback, run before the answer is sent), and report the interval
        :func:`revised_sampling` gives it as its RevisedSamplingInterval."""
        params = event.request_params
        subscription = self.server.iserver.subscription_service.subscriptions.get(params.SubscriptionId)
        if subscription is None:
            return
        items = subscription.monitored_item_srv._monitored_items
        publishing_ms = subscription.data.RevisedPublishingInterval
        tick_ms = 1000 * finite_period(self.source)
        created = isinstance(params, ua.CreateMonitoredItemsParameters)
        requests = params.ItemsToCreate if created else params.ItemsToModify
        for request, result in zip(requests, event.response_params, strict=False):
            mdata = items.get(result.MonitoredItemId if created else request.MonitoredItemId)
            if not result.StatusCode.is_good() or mdata is None or mdata.callback_handle is None:
                continue   # refused, or an event item
            honoured, reported = revised_sampling(request.RequestedParameters.SamplingInterval, publishing_ms,
                                                  tick_ms)
            self._intervals[mdata.callback_handle] = honoured / 1000
            result.RevisedSamplingInterval = reported
        self._dirty = True

    def _track_monitored_items(self) -> None:
        """Mark the list of monitored variables stale whenever asyncua adds or removes a data-change callback."""
        aspace = self.server.iserver.aspace
        add, delete = aspace.add_datachange_callback, aspace.delete_datachange_callback

        def added(*args: Any, **kwargs: Any) -> Any:
            self._dirty = True
            return add(*args, **kwargs)

        def deleted(handle: int, *args: Any, **kwargs: Any) -> Any:
            self._dirty = True
            self._intervals.pop(handle, None)
            self._resolved.pop(handle, None)
            return delete(handle, *args, **kwargs)

        aspace.add_datachange_callback, aspace.delete_datachange_callback = added, deleted

    # --- lifecycle -------------------------------------------------------------------------------------

    async def start(self) -> None:
        """Build the address space and listen, the device paused meanwhile (``source.paused``)."""
        async with self.source.paused():
            await self._start()

    async def _start(self) -> None:
        for logger in _asyncua_loggers():
            logger.addFilter(self._log_filter)
        sec = self.security
        users = UsersFile(users=sec.users or {}, anonymous=not sec.users)
        server = Server(user_manager=users)
        self.server = server
        await server.init()
        server.iserver.attribute_service = _CheckedWrites(server.iserver.aspace, self)
        server.set_server_name("valve_emulator")
        await server.set_application_uri(APPLICATION_URI)
        host = f"[{self.host}]" if ":" in self.host else self.host
        server.set_endpoint(f"opc.tcp://{host}:{self.port}/valve-emulator/")
        policies = []
        for name in sec.policies:
            policies.append(ua.SecurityPolicyType.NoSecurity if name == "None"
                            else getattr(ua.SecurityPolicyType, f"{name}_SignAndEncrypt"))
        server.set_security_policy(policies, permission_ruleset=RoleRuleset())
        tokens = [ua.UserNameIdentityToken] if sec.users else []
        if not sec.users:
            tokens.append(ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        if sec.certificate is not None:
            await server.load_certificate(str(sec.certificate))
            await server.load_private_key(str(sec.private_key))
        if sec.pki is not None or sec.trust_all:
            self.trust_list = TrustList(sec.pki, trust_all=sec.trust_all)
            self.trust_list.create()
            server.set_certificate_validator(self.trust_list)
        self.ns = await server.register_namespace(NAMESPACE)
        loop_type = await self._define_loop_type()
        objects = ua.NodeId(ua.ObjectIds.ObjectsFolder)
        station = self._object_item(objects, "ValveEmulator", "ValveEmulator")
        items, units = [station], {}
        for index, loop in enumerate(self.loops):
            unit = int(self.source.units[index])
            if unit not in units:
                units[unit] = self._object_item(station.RequestedNewNodeId, f"Unit{unit}", f"Unit{unit}")
                items.append(units[unit])
            items += self._loop_items(units[unit].RequestedNewNodeId, index, loop, loop_type)
        await self._add(items)
        self._serve_values()
        root = server.get_node(station.RequestedNewNodeId)
        await self._add_methods(root)
        self._track_monitored_items()
        for created_or_modified in (CallbackType.ItemSubscriptionCreated, CallbackType.ItemSubscriptionModified):
            server.subscribe_server_callback(created_or_modified, self._sampling_requested)
        if self.source.has_alarms:   # each loop's PV alarm as an AlarmConditionType condition
            self.alarm_conditions = AlarmConditions(self)
            await self.alarm_conditions.start()
        await server.start()
        if self.history is not None:
            await historize(server, self._historized, self.history, self.history_path)
        refuse_unhistorized(server, set(self._historized))
        self.port = int(server.bserver.port)
        self._publisher = asyncio.get_running_loop().create_task(
            self._publish_ahead() if self.hand_ahead else self._publish(), name="valve-emulator-opcua")
        _log.info("OPC UA on %s:%d", self.host, self.port)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}/valve-emulator/"

    async def stop(self) -> None:
        conditions, self.alarm_conditions = self.alarm_conditions, None
        if conditions is not None:
            await conditions.stop()
        task, self._publisher = self._publisher, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        server, self.server = self.server, None
        if server is not None:
            await _stop_clock_task(server)
            await server.stop()
        for logger in _asyncua_loggers():
            logger.removeFilter(self._log_filter)

    async def __aenter__(self) -> OpcUaServer:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.stop()
