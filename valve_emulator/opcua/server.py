"""OPC UA adapter: the same live loops as the Modbus server, as an OPC UA address space (asyncua).

The only module that knows OPC UA's wire format and address-space types. It serves the
:class:`~valve_emulator.device.tick.Device` that the Modbus server ticks, in the same process and event
loop, so a value written over one protocol is read over the other after the next tick.

Address space (namespace ``urn:valve-emulator``)::

    Objects
    └── ValveEmulator                         the station object: Freeze, Run, SetSpeed, Snapshot, Restore,
        │                                     InjectMalfunction (instructors only)
        └── Unit1                             one object per Modbus unit id
            └── FIC101   (LoopType)           one object per loop; the type is defined once under
                ├── op, mv, flow, S, J, load  ObjectTypes/BaseObjectType/LoopType
                ├── pv, sp, noise             AnalogItemType, Double, engineering units, EURange
                ├── kc, ti, td, time          AnalogItemType, Double
                ├── mode, status, fault, map_version, tick, overruns    BaseDataVariableType (integers)
                └── stuck, moving, sat_low, sat_high, seized            TwoStateDiscreteType (Boolean)

Every variable is derived from the register map (:data:`~valve_emulator.device.registers.REGISTERS`): one
variable per quantity, named after the quantity's 16-bit register (``op_pct`` → ``op``), read from the
register with the finest resolution (the float32 copy where there is one) and written through the first
writable register, so an OPC UA write is checked by exactly the code that checks a Modbus write
(:meth:`Device.write <valve_emulator.device.tick.Device.write>`). The bits are the ``status`` register's.

Writes answer:

- ``BadNotWritable``: a read-only variable, OP while the loop is in auto, a controller variable of a loop
  without controller;
- ``BadUserAccessDenied``: an instructor variable written by an operator;
- ``BadOutOfRange``: a value the register refuses (the Modbus ``0x03``); ``BadTypeMismatch``: not a number.

Values are read at request time from the register image (so a read sees a write at once, as over Modbus);
subscriptions are fed after every tick with the values that changed. ``SourceTimestamp`` is the simulated
time: the wall-clock time the server started plus the simulated seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.server.address_space import AttributeService

from valve_emulator.device.guard import binds_all_interfaces
from valve_emulator.device.registers import (
    CDAB,
    REGISTERS,
    RW_INSTRUCTOR,
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
from valve_emulator.opcua.users import RoleRuleset, StationUser, UsersFile

__all__ = ["OpcUaServer", "OpcUaSecurity", "NAMESPACE", "VARIABLES", "BITS", "OpcUaError"]

_log = logging.getLogger(__name__)

NAMESPACE = "urn:valve-emulator"
APPLICATION_URI = "urn:valve-emulator:server"
SECURE_POLICIES = ("Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss")


class OpcUaError(ValueError):
    """A server that must not start as configured (e.g. bound beyond loopback without security)."""


@dataclass(frozen=True)
class Variable:
    """One OPC UA variable of a loop: ``name`` (BrowseName), the register it is read from and the one it is
    written through (None: read-only), its units (``PV units`` resolves to the loop's) and data type."""

    name: str
    read: Register
    write: Register | None
    units: str
    analog: bool

    @property
    def variant(self) -> ua.VariantType:
        if self.analog:
            return ua.VariantType.Double
        return ua.VariantType.UInt32 if self.read.type is DataType.UINT32 else ua.VariantType.UInt16

    @property
    def instructor(self) -> bool:
        return self.write is not None and self.write.access is RW_INSTRUCTOR


def _variables() -> tuple[Variable, ...]:
    """One :class:`Variable` per quantity of the register map, in the map's order."""
    out: list[Variable] = []
    for quantity in dict.fromkeys(r.quantity for r in REGISTERS):
        showing = [r for r in REGISTERS if r.quantity == quantity]
        first = showing[0]
        read = next((r for r in showing if r.type is DataType.FLOAT32), first)
        write = next((r for r in showing if r.access is not R), None)
        analog = read.type is DataType.FLOAT32 or (first.scale > 1 and first.conversion.value != "bits")
        out.append(Variable(name=first.name.removesuffix("_pct"), read=read, write=write,
                            units=read.units if read.type is DataType.FLOAT32 else first.units, analog=analog))
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

# UNECE codes (OPC UA Part 8, EUInformation) of the units the map uses.
_UNECE = {"%": (20529, "%"), "% travel": (20529, "%"), "% flow": (20529, "%"), "s": (21315, "s"), "mA": (4747521, "mA"),
          "m": (5067858, "m"), "bar": (4342098, "bar"), "degC": (4408652, "°C"), "kg/h": (4933448, "kg/h")}


@dataclass(frozen=True)
class OpcUaSecurity:
    """How clients may connect.

    ``policies``: ``"None"`` and/or secure policy names (:data:`SECURE_POLICIES`, always Sign&Encrypt);
    ``certificate``/``private_key``: the application instance certificate (PEM or DER) and its key;
    ``users``: the users file's users (None: anonymous operators only).
    """

    policies: tuple[str, ...] = ("None",)
    certificate: Path | None = None
    private_key: Path | None = None
    users: dict | None = None

    def check(self, host: str) -> None:
        """Refuse a set-up that exposes the device: beyond loopback only secure policies with users."""
        unknown = [p for p in self.policies if p != "None" and p not in SECURE_POLICIES]
        if unknown:
            raise OpcUaError(f"opcua security policy {unknown[0]!r}: known are None, {', '.join(SECURE_POLICIES)}")
        secure = [p for p in self.policies if p != "None"]
        if secure and (self.certificate is None or self.private_key is None):
            raise OpcUaError(f"opcua: policy {secure[0]} needs a certificate and a private key "
                             "(make them with 'valve-emulator certs --opcua DIR')")
        if _loopback(host):
            return
        if "None" in self.policies or not secure or not self.users:
            raise OpcUaError(f"opcua: refusing to listen on {host!r} (beyond loopback) without security: configure "
                             f"a secure policy ({', '.join(SECURE_POLICIES)}, Sign&Encrypt), a certificate and a "
                             "users file, and drop policy None")


def _loopback(host: str) -> bool:
    import ipaddress

    if host == "localhost":
        return True
    if binds_all_interfaces(host):
        return False
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


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
            results.append(self._adapter.write(*target, item.Value, user))
        return results


class OpcUaServer:
    """Serve ``device`` over OPC UA: ``async with OpcUaServer(device, loops=..., port=0) as srv: srv.port``.

    Parameters
    ----------
    device : the running :class:`~valve_emulator.device.tick.Device`.
    loops : the loop configs, in the device's order (names, PV units, PV range).
    host, port : where to listen (port 0: a free port, read back from :attr:`port`).
    security : :class:`OpcUaSecurity` (default: policy None, anonymous operators; loopback only).
    station : an instructor station (``station.core.Station``) whose actions the methods call; None: no
        methods.
    """

    def __init__(self, device: Any, *, loops: Sequence[Any], host: str = "127.0.0.1", port: int = 0,
                 security: OpcUaSecurity | None = None, station: Any = None) -> None:
        self.device, self.loops, self.host, self.port = device, list(loops), host, int(port)
        self.security = security or OpcUaSecurity()
        self.security.check(host)
        self.station = station
        self.server: Server | None = None
        self.ns = 0
        #: NodeId -> (loop index, Variable) of every writable-or-not loop variable
        self.targets: dict[ua.NodeId, tuple[int, Variable]] = {}
        #: every node id this adapter created (for BadNotWritable on the others)
        self.node_ids: set[ua.NodeId] = set()
        self._monitored: list[tuple[Any, int, Callable[[int], ua.DataValue]]] = []
        self._sent: dict[int, Any] = {}
        self._epoch = datetime.now(UTC)
        self._publisher: asyncio.Task | None = None
        self._log_filter = RepeatFilter()
        self.writes = 0
        self.refused = 0

    # --- values -----------------------------------------------------------------------------------------

    def _words(self, index: int, reg: Register) -> Sequence[int]:
        start = int(self.device.offsets[index]) + 2 * reg.address
        raw = self.device.image[start:start + 2 * reg.width]
        return [int.from_bytes(raw[k:k + 2], "big") for k in range(0, len(raw), 2)]

    def value(self, index: int, var: Variable) -> float | int:
        """The variable's value now, from the register image, in engineering units."""
        words = self._words(index, var.read)
        order = self.device.scaling.word_order
        if var.read.type is DataType.FLOAT32:
            return float(from_words(words, DataType.FLOAT32, "CDAB" if order is CDAB else "ABCD"))
        if var.read.width == 2:
            return int(from_words(words, var.read.type, "CDAB" if order is CDAB else "ABCD"))
        raw = words[0] - 65536 if var.read.type is DataType.INT16 and words[0] >= 32768 else words[0]
        value = decode_value(var.read, raw, self.device.scaling, index)
        if var.analog:
            return float(value) if math.isfinite(value) else 0.0
        return int(value)

    def _timestamp(self) -> datetime:
        return self._epoch + timedelta(seconds=float(self.device.bank.sample_time))

    def _data_value(self, value: Any, variant: ua.VariantType) -> ua.DataValue:
        return ua.DataValue(Value=ua.Variant(value, variant), SourceTimestamp=self._timestamp(),
                            ServerTimestamp=datetime.now(UTC))

    def _reader(self, index: int, var: Variable) -> Callable[..., ua.DataValue]:
        return lambda *_: self._data_value(self.value(index, var), var.variant)

    def _bit_reader(self, index: int, bit: Status) -> Callable[..., ua.DataValue]:
        return lambda *_: self._data_value(bool(int(self.value(index, _STATUS)) & int(bit)), ua.VariantType.Boolean)

    # --- writes ---------------------------------------------------------------------------------------

    def write(self, index: int, var: Variable, dv: ua.DataValue, user: Any) -> ua.StatusCode:
        """One client write of ``var`` on loop ``index`` through ``Device.write``; the OPC UA status code."""
        if var.write is None:
            self.refused += 1
            return ua.StatusCode(ua.StatusCodes.BadNotWritable)
        value = dv.Value.Value if dv.Value is not None else None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            self.refused += 1
            return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
        instructor = isinstance(user, StationUser) and user.instructor
        if var.instructor and not instructor:
            self.refused += 1
            return ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
        try:
            words = encode_write(var.write, value, self.device.scaling, index)
            self.device.write(index, var.write.address, words, instructor=instructor)
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

    # --- address space --------------------------------------------------------------------------------

    async def _add_variable(self, parent: Any, name: str, value: Any, variant: ua.VariantType, typedef: int,
                            *, writable: bool = False, modelling: bool = False) -> ua.NodeId:
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = ua.NodeId(f"{parent.nodeid.Identifier}.{name}", self.ns)
        item.BrowseName = ua.QualifiedName(name, self.ns)
        item.NodeClass = ua.NodeClass.Variable
        item.ParentNodeId = parent.nodeid
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
        item.TypeDefinition = ua.NodeId(typedef)
        attrs = ua.VariableAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(name)
        attrs.DataType = ua.NodeId(int(variant.value))
        attrs.Value = ua.Variant(value, variant)
        attrs.ValueRank = ua.ValueRank.Scalar
        access = ua.AccessLevel.CurrentRead.mask | (ua.AccessLevel.CurrentWrite.mask if writable else 0)
        attrs.AccessLevel = attrs.UserAccessLevel = access
        item.NodeAttributes = attrs
        result = (await self.server.iserver.isession.add_nodes([item]))[0]
        result.StatusCode.check()
        node_id = result.AddedNodeId
        self.node_ids.add(node_id)
        if modelling:
            await self.server.get_node(node_id).set_modelling_rule(True)
        return node_id

    async def _add_object(self, parent: Any, node_id: str, name: str, typedef: ua.NodeId | None = None) -> Any:
        """An object under ``parent`` typed ``typedef`` (default BaseObjectType), without copying the type's
        children (the caller adds the loop's own variables, with the loop's ranges and units)."""
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = ua.NodeId(node_id, self.ns)
        item.BrowseName = ua.QualifiedName(name, self.ns)
        item.NodeClass = ua.NodeClass.Object
        item.ParentNodeId = parent.nodeid
        folder = parent.nodeid == ua.NodeId(ua.ObjectIds.ObjectsFolder)
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.Organizes if folder else ua.ObjectIds.HasComponent)
        item.TypeDefinition = typedef or ua.NodeId(ua.ObjectIds.BaseObjectType)
        attrs = ua.ObjectAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(name)
        item.NodeAttributes = attrs
        result = (await self.server.iserver.isession.add_nodes([item]))[0]
        result.StatusCode.check()
        self.node_ids.add(result.AddedNodeId)
        return self.server.get_node(result.AddedNodeId)

    async def _add_property(self, node_id: ua.NodeId, name: str, value: Any, variant: ua.VariantType,
                            datatype: int | None = None) -> None:
        node = self.server.get_node(node_id)
        prop = await node.add_property(ua.NodeId(f"{node_id.Identifier}.{name}", self.ns), ua.QualifiedName(name, 0),
                                       value, variant, datatype)
        self.node_ids.add(prop.nodeid)

    def _eu_range(self, loop: Any, var: Variable) -> tuple[float, float] | None:
        if "PV" in var.units or "pv_range" in var.units:
            return tuple(map(float, loop.plant.pv_range))
        if "%" in var.units:
            return (0.0, 100.0)
        return None

    def _units(self, loop: Any, var: Variable) -> str:
        if "PV units" in var.units:
            return str(loop.plant.units)
        if var.name == "noise":
            return str(loop.plant.units)
        return var.units

    async def _define_loop_type(self) -> Any:
        base = self.server.get_node(ua.ObjectIds.BaseObjectType)
        loop_type = await base.add_object_type(ua.NodeId("LoopType", self.ns), ua.QualifiedName("LoopType", self.ns))
        for var in VARIABLES:
            zero = 0.0 if var.analog else 0
            typedef = ua.ObjectIds.AnalogItemType if var.analog else ua.ObjectIds.BaseDataVariableType
            await self._add_variable(loop_type, var.name, zero, var.variant, typedef, writable=var.write is not None,
                                     modelling=True)
        for name in BITS:
            await self._add_variable(loop_type, name, False, ua.VariantType.Boolean, ua.ObjectIds.TwoStateDiscreteType,
                                     modelling=True)
        return loop_type

    async def _add_loop(self, unit_node: Any, index: int, loop: Any, loop_type: Any) -> None:
        aspace = self.server.iserver.aspace
        name = str(loop.name)
        obj = await self._add_object(unit_node, f"{unit_node.nodeid.Identifier}.{name}", name, loop_type.nodeid)
        for var in VARIABLES:
            typedef = ua.ObjectIds.AnalogItemType if var.analog else ua.ObjectIds.BaseDataVariableType
            node_id = await self._add_variable(obj, var.name, self.value(index, var), var.variant, typedef,
                                               writable=var.write is not None)
            if var.analog:
                rng = self._eu_range(loop, var)
                if rng is not None:
                    await self._add_property(node_id, "EURange", ua.Range(Low=rng[0], High=rng[1]),
                                             ua.VariantType.ExtensionObject, ua.ObjectIds.Range)
                units = self._units(loop, var)
                code, symbol = _UNECE.get(units, (-1, units))
                eu = ua.EUInformation(NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact", UnitId=code,
                                      DisplayName=ua.LocalizedText(symbol), Description=ua.LocalizedText(units))
                await self._add_property(node_id, "EngineeringUnits", eu, ua.VariantType.ExtensionObject,
                                         ua.ObjectIds.EUInformation)
            self.targets[node_id] = (index, var)
            reader = self._reader(index, var)
            aspace.set_attribute_value_callback(node_id, ua.AttributeIds.Value, reader)
            self._watch(node_id, reader)
        for name, (bit, true_state, false_state) in BITS.items():
            node_id = await self._add_variable(obj, name, False, ua.VariantType.Boolean,
                                               ua.ObjectIds.TwoStateDiscreteType)
            await self._add_property(node_id, "TrueState", ua.LocalizedText(true_state), ua.VariantType.LocalizedText)
            await self._add_property(node_id, "FalseState", ua.LocalizedText(false_state), ua.VariantType.LocalizedText)
            reader = self._bit_reader(index, bit)
            aspace.set_attribute_value_callback(node_id, ua.AttributeIds.Value, reader)
            self._watch(node_id, reader)

    def _watch(self, node_id: ua.NodeId, reader: Callable[..., ua.DataValue]) -> None:
        attval = self.server.iserver.aspace._nodes[node_id].attributes[ua.AttributeIds.Value]
        self._monitored.append((attval, len(self._monitored), reader))

    async def _add_methods(self, station_node: Any) -> None:
        if self.station is None:
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

    async def _guarded(self, action: Callable[[], Any]) -> list[ua.Variant] | ua.StatusCode:
        """Run a station action; its refusal (``StationError``, which names the field) becomes BadNotFound
        (an unknown snapshot) or BadInvalidArgument, and a result is handed back as JSON text."""
        try:
            result = action()
            if asyncio.iscoroutine(result):
                result = await result
        except Exception as exc:
            if not hasattr(exc, "field"):   # not the station's refusal: a bug, asyncua reports BadInternalError
                raise
            _log.info("OPC UA: station method refused: %s", exc)
            code = ua.StatusCodes.BadNotFound if getattr(exc, "status", 400) == 404 else \
                ua.StatusCodes.BadInvalidArgument
            return ua.StatusCode(code)   # asyncua answers a raised error as BadUnexpectedError
        return [] if result is None else [ua.Variant(json.dumps(result), ua.VariantType.String)]

    async def _freeze(self, parent: Any) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded(self.station.freeze)

    async def _run(self, parent: Any) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded(self.station.run)

    async def _set_speed(self, parent: Any, time_scale: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded(lambda: self.station.speed({"time_scale": time_scale.Value}))

    async def _snapshot(self, parent: Any, name: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded(lambda: self.station.save_snapshot({"name": name.Value}))

    async def _restore(self, parent: Any, name: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        return await self._guarded(lambda: self.station.restore_snapshot(name.Value))

    async def _inject(self, parent: Any, body: ua.Variant) -> list[ua.Variant] | ua.StatusCode:
        try:
            parsed = json.loads(body.Value)
        except (TypeError, ValueError):
            return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)
        return await self._guarded(lambda: self.station.malfunction(parsed))

    # --- publishing ------------------------------------------------------------------------------------

    async def _publish(self) -> None:
        """After every tick, hand the monitored variables whose value changed to their subscriptions."""
        device, seen = self.device, self.device.ticks
        while True:
            seen = await device.wait_for_tick(seen + 1)
            for attval, key, reader in self._monitored:
                callbacks = attval.datachange_callbacks
                if not callbacks:
                    continue
                dv = reader()
                value = dv.Value.Value
                if self._sent.get(key) == value:
                    continue
                self._sent[key] = value
                for handle, callback in list(callbacks.items()):
                    try:
                        await callback(handle, dv)
                    except Exception:   # one broken subscription must not stop the others
                        _log.exception("OPC UA: a data-change notification failed")

    # --- lifecycle -------------------------------------------------------------------------------------

    async def start(self) -> None:
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
        self.ns = await server.register_namespace(NAMESPACE)
        loop_type = await self._define_loop_type()
        root = await self._add_object(server.nodes.objects, "ValveEmulator", "ValveEmulator")
        units: dict[int, Any] = {}
        for index, loop in enumerate(self.loops):
            unit = int(self.device.units[index])
            if unit not in units:
                units[unit] = await self._add_object(root, f"Unit{unit}", f"Unit{unit}")
            await self._add_loop(units[unit], index, loop, loop_type)
        await self._add_methods(root)
        await server.start()
        self.port = int(server.bserver.port)
        self._publisher = asyncio.get_running_loop().create_task(self._publish(), name="valve-emulator-opcua")
        _log.info("OPC UA on %s:%d", self.host, self.port)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}/valve-emulator/"

    async def stop(self) -> None:
        task, self._publisher = self._publisher, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        server, self.server = self.server, None
        if server is not None:
            await server.stop()
        for logger in _asyncua_loggers():
            logger.removeFilter(self._log_filter)

    async def __aenter__(self) -> OpcUaServer:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self.stop()
