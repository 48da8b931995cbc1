"""The OPC UA server beside Modbus: address space, writes through the register map's checks, both directions,
roles, the station's methods and subscriptions; asyncua's client in process."""

import asyncio
import json
import math
import time

import pytest
from asyncua import Client, ua
from pymodbus.client import AsyncModbusTcpClient

from valve_emulator.device.registers import REGISTERS, address_of
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.snapshots import SnapshotStore
from valve_emulator.opcua import NAMESPACE, OpcUaError, OpcUaSecurity, hash_password
from valve_emulator.opcua.alarms import CONDITION_NAME
from valve_emulator.opcua.server import BITS, VARIABLES
from valve_emulator.station.core import Station

from .conftest import ON_A_SHARED_SERVER, restored, shared_server
from .modes import serve_opcua

USERS = {"ines": ("instructor", hash_password("teach", iterations=1000)),
         "otto": ("operator", hash_password("run", iterations=1000))}


def _users():
    from valve_emulator.device.roles import DEFAULT_ROLES

    return {name: (DEFAULT_ROLES.get(role), stored) for name, (role, stored) in USERS.items()}


@pytest.fixture
async def served(opcua_mode, config):
    """(Modbus server, OPC UA server) on one device, time frozen: the test steps it with ``device.advance``.
    A server of the test's own: the test counts refusals from zero or follows the clock from its start."""
    async with EmulatorServer(config, port=0, time_scale=0) as srv:
        station = Station(srv.device, snapshots=SnapshotStore())
        async with serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0, station=station) as opc:
            yield srv, opc


_shared_served = shared_server()


@pytest.fixture
def shared(_shared_served):
    """Like ``served``, one server per mode for the module's tests that count nothing; each test gets the
    device back as it was before the previous one."""
    srv, _, opc = _shared_served
    with restored(srv.device):
        yield srv, opc


async def _loop_node(client, unit, name):
    ns = await client.get_namespace_index(NAMESPACE)
    return await client.nodes.objects.get_child([f"{ns}:ValveEmulator", f"{ns}:Unit{unit}", f"{ns}:{name}"]), ns


async def _modbus_read(port, name, unit):
    async with AsyncModbusTcpClient("127.0.0.1", port=port) as mb:
        rr = await mb.read_holding_registers(address_of(name), count=1, device_id=unit)
        assert not rr.isError()
        return rr.registers[0]


@ON_A_SHARED_SERVER
async def test_address_space_is_the_register_map_with_units_and_ranges(shared, config):
    srv, opc = shared
    async with Client(opc.url) as client:
        loop, ns = await _loop_node(client, 1, "FIC101")
        names = {(await c.read_browse_name()).Name for c in await loop.get_children()}
        # every quantity of the register map, under its 16-bit register's name, the status bits and the PV
        # alarm's condition object
        assert names == {v.name for v in VARIABLES} | set(BITS) | {CONDITION_NAME}
        assert {"pv", "sp", "op", "mv", "mode", "S", "J", "kc", "ti", "load", "fault", "stuck", "seized"} <= names
        assert len(VARIABLES) == len({r.quantity for r in REGISTERS})
        type_def = await loop.read_type_definition()
        assert (await client.get_node(type_def).read_browse_name()).Name == "LoopType"
        pv = await loop.get_child(f"{ns}:pv")
        assert await pv.read_type_definition() == ua.NodeId(ua.ObjectIds.AnalogItemType)
        assert (await pv.read_data_type()) == ua.NodeId(ua.ObjectIds.Double)
        rng = await (await pv.get_child("0:EURange")).read_value()
        assert (rng.Low, rng.High) == (0.0, 50.0)
        eu = await (await pv.get_child("0:EngineeringUnits")).read_value()
        assert (eu.DisplayName.Text, eu.UnitId) == ("m³/h", 5067080)   # UNECE MQH, cubic metre per hour
        stuck = await loop.get_child(f"{ns}:stuck")
        assert await stuck.read_type_definition() == ua.NodeId(ua.ObjectIds.TwoStateDiscreteType)
        assert isinstance(await stuck.read_value(), bool)
        # values are the device's, in engineering units
        assert await (await loop.get_child(f"{ns}:S")).read_value() == pytest.approx(5.0)
        assert await pv.read_value() == pytest.approx(float(srv.device.bank.pv[0]), abs=1e-4)


@ON_A_SHARED_SERVER
async def test_a_write_over_opcua_is_read_over_modbus_and_the_other_way(shared):
    srv, opc = shared
    async with Client(opc.url) as client:
        loop, ns = await _loop_node(client, 2, "XV2")
        op = await loop.get_child(f"{ns}:op")
        await op.write_value(ua.DataValue(ua.Variant(62.5, ua.VariantType.Double)))
        srv.device.advance(1)
        assert await _modbus_read(srv.port, "op_pct", 2) == 6250
        assert float(srv.device.bank.op[1]) == pytest.approx(62.5)
        async with AsyncModbusTcpClient("127.0.0.1", port=srv.port) as mb:
            assert not (await mb.write_register(address_of("op_pct"), 3125, device_id=2)).isError()
        srv.device.advance(1)
        assert await op.read_value() == pytest.approx(31.25)


REFUSED = [
    (1, "FIC101", "op", 40.0, "BadNotWritable"),          # OP while the controller is in auto
    (1, "FIC101", "pv", 10.0, "BadNotWritable"),          # read-only
    (1, "FIC101", "stuck", True, "BadNotWritable"),       # a status bit
    (1, "FIC101", "S", 1.0, "BadUserAccessDenied"),       # instructor variable, anonymous operator
    (2, "XV2", "op", 150.0, "BadOutOfRange"),             # beyond 100 % travel: refused, not clipped
    (2, "XV2", "sp", 1.0, "BadNotWritable"),              # controller variable of a loop without one
    (1, "FIC101", "kc", 1.0, "BadUserAccessDenied"),      # tuning: not an operator's
    (1, "FIC101", "sp", 80.0, "BadOutOfRange"),           # outside pv_range 0..50
    (2, "XV2", "op", "50", "BadTypeMismatch"),            # not a number
]


async def test_refused_writes_answer_a_bad_status_and_change_nothing(served):
    srv, opc = served
    image = bytes(srv.device.image)
    async with Client(opc.url) as client:
        for refused, (unit, name, var, value, code) in enumerate(REFUSED, start=1):
            loop, ns = await _loop_node(client, unit, name)
            node = await loop.get_child(f"{ns}:{var}")
            variant = {bool: ua.VariantType.Boolean, str: ua.VariantType.String}.get(type(value), ua.VariantType.Double)
            with pytest.raises(ua.UaStatusCodeError) as err:
                await node.write_value(ua.DataValue(ua.Variant(value, variant)))
            assert (var, type(err.value).__name__) == (var, code)
            assert (await opc.counters()).refused == refused
    assert bytes(srv.device.image) == image
    srv.device.advance(1)
    assert float(srv.device.bank.op[1]) != 150.0 and float(srv.device.bank.S[0]) == 5.0


@ON_A_SHARED_SERVER
async def test_operator_may_not_call_the_station_methods(shared):
    srv, opc = shared
    async with Client(opc.url) as client:
        ns = await client.get_namespace_index(NAMESPACE)
        station = await client.nodes.objects.get_child(f"{ns}:ValveEmulator")
        with pytest.raises(ua.UaStatusCodeError) as err:
            body = json.dumps({"unit": 1, "kind": "sensor_drift", "bias": 1.0})
            await station.call_method(f"{ns}:InjectMalfunction", body)
        assert type(err.value).__name__ == "BadUserAccessDenied"
        with pytest.raises(ua.UaStatusCodeError):
            await station.call_method(f"{ns}:Freeze")
    assert float(srv.device.bank.pv_bias[0]) == 0.0


@ON_A_SHARED_SERVER
async def test_subscription_notifies_pv_after_ticks(shared):
    srv, opc = shared
    got = []

    class Handler:
        def datachange_notification(self, node, val, data):
            got.append((val, data.monitored_item.Value.SourceTimestamp))

    async with Client(opc.url) as client:
        loop, ns = await _loop_node(client, 2, "XV2")
        sub = await client.create_subscription(50, Handler())
        await sub.subscribe_data_change(await loop.get_child(f"{ns}:time"))
        await asyncio.sleep(0.3)
        first = len(got)
        for _ in range(3):
            srv.device.advance(10)
            await asyncio.sleep(0.2)
        assert len(got) >= first + 3
        values = [v for v, _ in got]
        assert values == sorted(values) and values[-1] == pytest.approx(2.9, abs=1e-3)  # sample time of tick 30
        await sub.delete()


_shared_secured = shared_server(security=OpcUaSecurity(users=_users()))


@pytest.fixture
def secured(_shared_secured):
    """Like ``shared``, with a users file: no anonymous access."""
    srv, _, opc = _shared_secured
    with restored(srv.device):
        yield srv, opc


async def _connect(url, user=None, password=None):
    client = Client(url)
    if user is not None:
        client.set_user(user)
        client.set_password(password)
    await client.connect()
    return client


@ON_A_SHARED_SERVER
async def test_with_users_anonymous_and_wrong_passwords_are_refused(secured):
    srv, opc = secured
    with pytest.raises(ua.UaStatusCodeError):
        await _connect(opc.url)
    with pytest.raises(ua.UaStatusCodeError):
        await _connect(opc.url, "ines", "wrong")
    with pytest.raises(ua.UaStatusCodeError):
        await _connect(opc.url, "nobody", "teach")


@ON_A_SHARED_SERVER
async def test_operator_cannot_write_S_and_instructor_can_and_may_inject(secured):
    srv, opc = secured
    operator = await _connect(opc.url, "otto", "run")
    try:
        loop, ns = await _loop_node(operator, 1, "FIC101")
        with pytest.raises(ua.UaStatusCodeError) as err:
            await (await loop.get_child(f"{ns}:S")).write_value(ua.DataValue(ua.Variant(1.0, ua.VariantType.Double)))
        assert type(err.value).__name__ == "BadUserAccessDenied"
        # what an operator may do: set point (PV units) within the range
        await (await loop.get_child(f"{ns}:sp")).write_value(ua.DataValue(ua.Variant(20.0, ua.VariantType.Double)))
    finally:
        await operator.disconnect()
    instructor = await _connect(opc.url, "ines", "teach")
    try:
        loop, ns = await _loop_node(instructor, 1, "FIC101")
        await (await loop.get_child(f"{ns}:S")).write_value(ua.DataValue(ua.Variant(1.5, ua.VariantType.Double)))
        station = await instructor.nodes.objects.get_child(f"{ns}:ValveEmulator")
        out = await station.call_method(f"{ns}:InjectMalfunction",
                                        json.dumps({"unit": 2, "kind": "sensor_drift", "bias": 1.0}))
        assert json.loads(out)["kind"] == "sensor_drift"
        summary = json.loads(await station.call_method(f"{ns}:Snapshot", "before"))
        assert summary["name"] == "before"
        await station.call_method(f"{ns}:Freeze")
        with pytest.raises(ua.UaStatusCodeError) as err:   # the station's own checks: an unknown snapshot
            await station.call_method(f"{ns}:Restore", "nope")
        assert type(err.value).__name__ == "BadNotFound"
        with pytest.raises(ua.UaStatusCodeError) as err:
            await station.call_method(f"{ns}:SetSpeed", ua.Variant(1e9, ua.VariantType.Double))
        assert type(err.value).__name__ == "BadInvalidArgument"
    finally:
        await instructor.disconnect()
    srv.device.advance(1)
    assert float(srv.device.bank.S[0]) == pytest.approx(1.5)
    assert float(srv.device.bank._sp[0]) == pytest.approx(20.0)
    assert float(srv.device.bank.pv_bias[1]) == pytest.approx(1.0)


def test_beyond_loopback_needs_a_secure_policy_and_users(tmp_path):
    with pytest.raises(OpcUaError, match="beyond loopback"):
        OpcUaSecurity().check("0.0.0.0")
    with pytest.raises(OpcUaError, match="certificate"):
        OpcUaSecurity(policies=("Basic256Sha256",), users=_users()).check("0.0.0.0")
    with pytest.raises(OpcUaError, match="beyond loopback"):
        OpcUaSecurity(policies=("Basic256Sha256",), certificate=tmp_path / "c", private_key=tmp_path / "k",
                      pki=tmp_path / "pki").check("::")
    OpcUaSecurity(policies=("Basic256Sha256",), certificate=tmp_path / "c", private_key=tmp_path / "k",
                  users=_users(), pki=tmp_path / "pki").check("0.0.0.0")
    OpcUaSecurity().check("127.0.0.1")
    OpcUaSecurity().check("::1")
    assert math.isfinite(1.0)


async def test_stopping_opcua_ends_its_tasks_at_once(opcua_mode, config, no_task_leak):
    """asyncua's own stop waits for the once-a-second clock task to wake up; the server ends it instead, so that
    neither a user's shutdown nor a test waits a second for nothing."""
    async with EmulatorServer(config, port=0, time_scale=0) as srv:
        opc = serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0)
        await opc.start()
        started = time.monotonic()
        await opc.stop()
        assert time.monotonic() - started < 0.5


@pytest.mark.realtime
async def test_starting_opcua_beside_a_running_device_costs_no_overrun(opcua_mode, config):
    """Building the address space keeps the event loop busy for a while: the tick waits (frozen) instead of
    running late, and runs on afterwards."""
    async with EmulatorServer(config, port=0, time_scale=1.0) as srv:
        await srv.device.wait_for_tick(2)
        overruns = srv.device.overruns
        async with serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0):
            assert not srv.device.frozen
            ticks = srv.device.ticks
            await srv.device.wait_for_tick(ticks + 3)
        assert srv.device.overruns == overruns
