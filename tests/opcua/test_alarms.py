"""PV alarms: one state, computed by the device, shown by the station, the Modbus ``alarms`` register and OPC UA
``AlarmConditionType`` events, acknowledged from any of them."""

import asyncio

import numpy as np
import pytest
from asyncua import Client, ua
from pymodbus.client import AsyncModbusTcpClient

from valve_emulator.device.alarms import AlarmState, PvAlarms
from valve_emulator.device.malfunctions import parse_malfunction
from valve_emulator.device.registers import AlarmBit, address_of
from valve_emulator.device.server import EmulatorServer
from valve_emulator.device.snapshots import SnapshotError, SnapshotStore
from valve_emulator.opcua import NAMESPACE
from valve_emulator.opcua.alarms import SEVERITY_ACTIVE
from valve_emulator.station.core import Station

from .conftest import ON_A_SHARED_SERVER, restored, shared_server
from .modes import serve_opcua

HIGH, LOW, UNACKED = int(AlarmBit.PV_HIGH), int(AlarmBit.PV_LOW), int(AlarmBit.UNACKED)
ACK = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)


# --- the state machine ---------------------------------------------------------------------------------------

def test_an_alarm_latches_until_acknowledged_and_back_inside_its_limits():
    alarms = PvAlarms([0.0, 0.0], [10.0, 10.0])
    seen = []
    alarms.listeners.append(seen.append)
    states = []
    for pv in ([5, 5], [11, 5], [12, 5], [5, 5]):
        alarms.update(np.array(pv, dtype=float))
        states.append(alarms.state(0))
    assert states == [AlarmState.NORMAL, AlarmState.UNACKED, AlarmState.UNACKED, AlarmState.RETURNED]
    assert [(c.index, c.word) for c in seen] == [(0, HIGH | UNACKED), (0, UNACKED)]   # only changes are told
    assert alarms.acknowledge(0) and alarms.state(0) is AlarmState.NORMAL
    assert not alarms.acknowledge(0)                   # nothing left to acknowledge: no change, no listener call
    alarms.update(np.array([-1.0, 5.0]))
    assert alarms.acknowledge(0) and alarms.state(0) is AlarmState.ACKED and int(alarms.words[0]) == LOW
    alarms.update(np.array([-2.0, 5.0]))               # still low, already acknowledged: stays acknowledged
    assert alarms.state(0) is AlarmState.ACKED
    alarms.update(np.array([5.0, 5.0]))
    assert alarms.state(0) is AlarmState.NORMAL and seen[-1].acknowledged is False
    assert alarms.state(1) is AlarmState.NORMAL


def test_a_snapshots_alarm_words_are_checked_before_they_are_used():
    alarms = PvAlarms([0.0], [1.0])
    assert alarms.checked_words(None) is None
    assert alarms.checked_words([HIGH | UNACKED]).tolist() == [5]
    for bad in ([8], [1, 1], ["1"], [True], "5"):
        with pytest.raises(ValueError, match="alarms must be 1 whole numbers 0..7"):
            alarms.checked_words(bad)


# --- served: Modbus, the station, OPC UA ------------------------------------------------------------------------

def _stick_sensor(device, unit: int, value: float) -> None:
    device.inject(parse_malfunction({"unit": unit, "kind": "sensor_stuck", "value": value},
                                    unit_index=device.unit_index, scaling=device.scaling))


def _clear(device, unit: int) -> None:
    device.inject(parse_malfunction({"unit": unit, "kind": "clear"}, unit_index=device.unit_index,
                                    scaling=device.scaling))


async def _alarms_word(port: int, unit: int, table: str = "holding") -> int:
    async with AsyncModbusTcpClient("127.0.0.1", port=port) as mb:
        read = mb.read_holding_registers if table == "holding" else mb.read_input_registers
        rr = await read(address_of("alarms"), count=1, device_id=unit)
        assert not rr.isError(), rr
        return rr.registers[0]


@pytest.fixture
async def served(opcua_mode, config):
    """(Modbus server, station, OPC UA server) on one device, time frozen (the test steps it). A server of the
    test's own: the test follows the OPC UA events of the alarm or counts the acknowledgements."""
    async with EmulatorServer(config, port=0, time_scale=0) as srv:
        station = Station(srv.device, snapshots=SnapshotStore())
        async with serve_opcua(opcua_mode, srv.device, loops=config.loops, port=0, station=station) as opc:
            yield srv, station, opc


_shared_served = shared_server()


@pytest.fixture
def shared(_shared_served):
    """Like ``served``, one server per mode for the module's tests that read the alarm over Modbus and the
    station; each test gets the device (its alarms too) back as it was before the previous one."""
    with restored(_shared_served[0].device):
        yield _shared_served


@ON_A_SHARED_SERVER
async def test_the_alarms_register_follows_pv_and_the_stations_acknowledgement(shared):
    srv, station, _ = shared
    _stick_sensor(srv.device, 2, 9.5)            # XV2: PV range -10..10, alarm limits -8..8
    srv.device.advance(1)
    assert await _alarms_word(srv.port, 2) == HIGH | UNACKED
    assert await _alarms_word(srv.port, 2, "input") == HIGH | UNACKED
    assert station.acknowledge(2) == {"unit": 2, "alarm": "acked"}
    assert await _alarms_word(srv.port, 2) == HIGH
    _clear(srv.device, 2)
    srv.device.advance(2)
    assert await _alarms_word(srv.port, 2) == 0
    assert station.loops_state([1], instructor=False)[0]["alarm"] == "normal"


@ON_A_SHARED_SERVER
async def test_a_snapshot_restores_the_alarm_and_a_forged_one_is_refused(shared):
    srv, station, _ = shared
    _stick_sensor(srv.device, 2, -9.0)
    srv.device.advance(1)
    snap = srv.device.snapshot("low")
    station.acknowledge(2)
    srv.device.restore(snap)
    assert await _alarms_word(srv.port, 2) == LOW | UNACKED
    forged = type(snap)(name="forged", time=snap.time, ticks=snap.ticks, bank=snap.bank,
                        device={**snap.device, "alarms": [99, 0]})
    with pytest.raises(SnapshotError, match="alarms must be 2 whole numbers"):
        srv.device.restore(forged)


class _Events:
    def __init__(self) -> None:
        self.queue: asyncio.Queue = asyncio.Queue()

    def event_notification(self, event) -> None:
        self.queue.put_nowait(event.get_event_props_as_fields_dict())

    async def next(self, source: str) -> dict:
        while True:
            fields = await asyncio.wait_for(self.queue.get(), 10)
            if fields["SourceName"].Value == source:
                return {k: v.Value for k, v in fields.items()}


async def _subscribe(client: Client) -> tuple[_Events, object]:
    events = _Events()
    sub = await client.create_subscription(20, events)
    await sub.subscribe_events(client.nodes.server, ua.ObjectIds.AlarmConditionType)
    return events, sub


async def test_opc_ua_clients_receive_alarm_events_and_acknowledge_them(served):
    srv, station, opc = served
    async with Client(opc.url) as client:
        events, _ = await _subscribe(client)
        _stick_sensor(srv.device, 2, 9.5)
        srv.device.advance(1)
        raised = await events.next("XV2")
        assert raised["EventType"] == ua.NodeId(ua.ObjectIds.AlarmConditionType)
        ns = await client.get_namespace_index(NAMESPACE)
        assert raised["NodeId"] == ua.NodeId("Unit2.XV2.PvAlarm", ns)
        assert raised["SourceNode"] == ua.NodeId("Unit2.XV2", ns)
        assert (raised["ActiveState/Id"], raised["AckedState/Id"], raised["Retain"]) == (True, False, True)
        assert raised["Severity"] == SEVERITY_ACTIVE
        assert raised["Message"].Text == "XV2: PV 9.5 above its high limit 8"

        condition = client.get_node(raised["NodeId"])
        with pytest.raises(ua.uaerrors.BadEventIdUnknown):
            await condition.call_method(ACK, ua.Variant(b"not-the-event", ua.VariantType.ByteString),
                                        ua.LocalizedText("wrong event"))
        await condition.call_method(ACK, ua.Variant(raised["EventId"], ua.VariantType.ByteString),
                                    ua.LocalizedText("seen it"))
        acked = await events.next("XV2")
        assert (acked["ActiveState/Id"], acked["AckedState/Id"], acked["Retain"]) == (True, True, True)
        assert station.loops_state([1], instructor=False)[0]["alarm"] == "acked"
        assert await _alarms_word(srv.port, 2) == HIGH
        assert [a.who for a in station.evaluation.actions if a.action == "ack"] == ["opcua"]
        with pytest.raises(ua.uaerrors.BadConditionBranchAlreadyAcked):
            await condition.call_method(ACK, ua.Variant(acked["EventId"], ua.VariantType.ByteString),
                                        ua.LocalizedText("again"))

        _clear(srv.device, 2)
        srv.device.advance(2)
        back = await events.next("XV2")
        assert (back["ActiveState/Id"], back["AckedState/Id"], back["Retain"]) == (False, True, False)


async def test_a_client_that_subscribes_late_gets_the_alarms_that_need_attention_on_refresh(served):
    srv, _, opc = served
    _stick_sensor(srv.device, 2, -9.5)
    srv.device.advance(1)                         # raised before anyone subscribed
    async with Client(opc.url) as client:
        events, sub = await _subscribe(client)
        await client.get_node(ua.ObjectIds.ConditionType).call_method(
            ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
            ua.Variant(sub.subscription_id, ua.VariantType.UInt32))
        refreshed = await events.next("XV2")
        assert (refreshed["ActiveState/Id"], refreshed["AckedState/Id"]) == (True, False)
        assert refreshed["Message"].Text.startswith("XV2: PV -9.5 below its low limit -8")
