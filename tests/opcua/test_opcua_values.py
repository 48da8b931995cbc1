"""What a SCADA reads from the OPC UA server: UNECE engineering units, doubles without float32 rounding,
timestamps of the tick that made a value, and an Uncertain status outside the engineering range; asyncua's
client in process."""

import asyncio
from datetime import UTC, datetime

import numpy as np
import pytest
from asyncua import Client, ua

from valve_emulator.opcua import NAMESPACE
from valve_emulator.opcua.units import UNITS, eu_information

from .conftest import ON_A_SHARED_SERVER, restored, shared_server

CEFACT = "http://www.opcfoundation.org/UA/units/un/cefact"

# UN/CEFACT Recommendation 20 common codes and the EUInformation.UnitId OPC UA Part 8 (§5.6.3) gives them: the
# code's characters packed into an Int32, one byte each, first character highest. SEC and 4K as OPC UA's
# UNECE_to_OPCUA table publishes them; the others packed by hand from the rule (checked below).
PUBLISHED = [
    ("s", "SEC", 5457219),       # second
    ("mA", "4K", 13387),         # milliampere
    ("kg/h", "E93", 4536627),    # kilogram per hour
    ("%", "P1", 20529),          # percent
    ("% travel", "P1", 20529),
    ("m", "MTR", 5067858),       # metre
    ("bar", "BAR", 4342098),
    ("degC", "CEL", 4408652),    # degree Celsius
    ("kg/m3", "KMQ", 4934993),   # kilogram per cubic metre
    ("m3/h", "MQH", 5067080),    # cubic metre per hour
    ("ms", "C26", 4403766),      # millisecond
]


@pytest.mark.parametrize(("text", "code", "unit_id"), PUBLISHED)
def test_unit_ids_are_the_unece_common_codes_packed_as_part_8_says(text, code, unit_id):
    # the rule, independently of the server: 'S','E','C' = 0x53,0x45,0x43 -> 0x534543
    assert int.from_bytes(code.encode("ascii"), "big") == unit_id
    eu = eu_information(text, own_namespace=NAMESPACE)
    assert (eu.NamespaceUri, eu.UnitId) == (CEFACT, unit_id)
    assert UNITS[text].code == code


def test_a_unit_text_unece_lacks_gets_no_guessed_code_and_no_units_none_at_all():
    eu = eu_information("furlong/fortnight", own_namespace=NAMESPACE)
    assert eu.UnitId == -1 and eu.DisplayName.Text == "furlong/fortnight" and eu.NamespaceUri != CEFACT
    assert eu_information("MA", own_namespace=NAMESPACE).UnitId == -1   # case matters: not mA
    assert eu_information("  ", own_namespace=NAMESPACE) is None


_shared_served = shared_server(with_station=False)


@pytest.fixture
def shared(_shared_served):
    """(Modbus server, OPC UA server) on one device, time frozen: the test steps it with ``device.advance``.
    One server per mode for the module's tests; each test gets the device back as it was before the previous
    one."""
    srv, _, opc = _shared_served
    with restored(srv.device):
        yield srv, opc


async def _variables(client, unit, name):
    ns = await client.get_namespace_index(NAMESPACE)
    loop = await client.nodes.objects.get_child([f"{ns}:ValveEmulator", f"{ns}:Unit{unit}", f"{ns}:{name}"])
    return {(await c.read_browse_name()).Name: c for c in await loop.get_children()}


async def _property(node, name):
    return await (await node.get_child(f"0:{name}")).read_value()


@ON_A_SHARED_SERVER
async def test_every_analog_variable_carries_its_unece_unit_and_range(shared):
    """FIC101's PV is in m3/h over 0..50; XV2's PV has no units."""
    srv, opc = shared
    async with Client(opc.url) as client:
        fic = await _variables(client, 1, "FIC101")
        served_units = {name: (await _property(fic[name], "EngineeringUnits")) for name in
                        ("op", "mv", "flow", "S", "J", "load", "ti", "td", "time", "pv", "sp", "noise", "kc")}
        ids = {name: eu.UnitId for name, eu in served_units.items()}
        assert ids == {"op": 20529, "mv": 20529, "flow": 20529, "S": 20529, "J": 20529, "load": 20529,
                       "ti": 5457219, "td": 5457219, "time": 5457219,
                       "pv": 5067080, "sp": 5067080, "noise": 5067080,
                       "kc": -1}   # % per m3/h: no UNECE unit
        assert served_units["kc"].DisplayName.Text == "% per m3/h"
        assert {eu.NamespaceUri for name, eu in served_units.items() if name != "kc"} == {CEFACT}
        ranges = {name: await _property(fic[name], "EURange") for name in ("op", "load", "pv", "noise")}
        assert {name: (r.Low, r.High) for name, r in ranges.items()} == {
            "op": (0.0, 100.0), "load": (-100.0, 100.0), "pv": (0.0, 50.0), "noise": (0.0, 50.0)}
        with pytest.raises(ua.UaStatusCodeError):   # the tuning and the clock have no engineering range
            await fic["kc"].get_child("0:EURange")
        xv = await _variables(client, 2, "XV2")
        with pytest.raises(ua.UaStatusCodeError):   # no PV units configured: no EngineeringUnits guessed
            await xv["pv"].get_child("0:EngineeringUnits")
        assert (await _property(xv["op"], "EngineeringUnits")).UnitId == 20529


@ON_A_SHARED_SERVER
async def test_float32_registers_are_shared_as_the_doubles_the_tick_computed(shared):
    srv, opc = shared
    device = srv.device
    async with Client(opc.url) as client:
        xv = await _variables(client, 2, "XV2")
        # a write shows at once, before the tick applies it: the value written, not its float32 (61.29999924)
        await xv["op"].write_value(ua.DataValue(ua.Variant(61.3, ua.VariantType.Double)))
        assert await xv["op"].read_value() == 61.3
        device.advance(14)   # sample time 13 × 0.1 s; PV on its way to the new OP's steady state
        time_value = await xv["time"].read_value()
        assert time_value == pytest.approx(1.3, abs=1e-12)   # the float32 register holds 1.2999999523
        pv = await xv["pv"].read_value()
        assert pv == float(device.bank.pv[1]) and pv != float(np.float32(pv))
        assert await xv["op"].read_value() == float(device.bank.op[1])


@ON_A_SHARED_SERVER
async def test_source_timestamp_is_the_wall_clock_time_of_the_tick_and_server_timestamp_the_read(shared):
    srv, opc = shared
    async with Client(opc.url) as client:
        time_node = (await _variables(client, 2, "XV2"))["time"]
        await asyncio.sleep(1.0)   # the server has been up a while: its start is not the tick's time
        ticked = datetime.now(UTC)
        srv.device.advance(50)     # lockstep: five simulated seconds now
        first = await time_node.read_data_value()
        await asyncio.sleep(0.5)
        again = await time_node.read_data_value()
    assert abs((first.SourceTimestamp - ticked).total_seconds()) < 0.2
    assert again.SourceTimestamp == first.SourceTimestamp   # no tick since: the same value, made then
    assert (again.ServerTimestamp - first.ServerTimestamp).total_seconds() >= 0.5   # each read is stamped anew


@ON_A_SHARED_SERVER
async def test_a_value_outside_its_engineering_range_is_uncertain(shared):
    """XV2's PV range is -10..10; OP from 50 to 100 % adds about 50 % flow, and PV (gain 1) leaves the range."""
    srv, opc = shared
    got = []

    class Handler:
        def datachange_notification(self, node, val, data):
            got.append((val, data.monitored_item.Value.StatusCode))

    async with Client(opc.url) as client:
        xv = await _variables(client, 2, "XV2")
        inside = await xv["pv"].read_data_value()
        assert inside.StatusCode.is_good() and -10 <= inside.Value.Value <= 10
        sub = await client.create_subscription(50, Handler())
        await sub.subscribe_data_change(xv["pv"])
        await xv["op"].write_value(ua.DataValue(ua.Variant(100.0, ua.VariantType.Double)))
        srv.device.advance(400)
        outside = await xv["pv"].read_data_value(raise_on_bad_status=False)
        assert outside.Value.Value > 10
        assert outside.StatusCode.value == ua.StatusCodes.UncertainEngineeringUnitsExceeded
        op = await xv["op"].read_data_value()   # 100 % is the top of OP's range, still inside
        assert op.Value.Value == 100.0 and op.StatusCode.is_good()
        for _ in range(20):
            if got and got[-1][0] > 10:
                break
            await asyncio.sleep(0.05)
        await sub.delete()
    assert got[-1][0] > 10 and got[-1][1].value == ua.StatusCodes.UncertainEngineeringUnitsExceeded


def _float32_served(order: str, written_op: float) -> tuple[dict, dict]:
    """A device in word order ``order`` after 5 ticks with PV noise and ``written_op`` written to XV2's OP since:
    (what the server serves, what the image and the bank give by the rule) for every float32 variable and loop."""
    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.registers import DataType, encode_write, from_words
    from valve_emulator.device.tick import Device
    from valve_emulator.opcua import LocalSource, OpcUaServer
    from valve_emulator.opcua.server import VARIABLES

    from .conftest import DEVICE

    config = server_from_mapping({**DEVICE, "device": {"tick": 0.1, "word_order": order}})
    device = Device.from_config(config, time_scale=0)
    device.bank.set_noise(0, 0.3)
    device.advance(5)
    source = LocalSource(device)
    server = OpcUaServer(source, loops=config.loops)
    op = next(v for v in VARIABLES if v.name == "op")
    device.write(1, op.write.address, encode_write(op.write, written_op, device.scaling, 1))
    served, rule = {}, {}
    for index in range(2):
        for var in (v for v in VARIABLES if v.read.type is DataType.FLOAT32):
            start = int(device.offsets[index]) + 2 * var.read.address
            words = [int.from_bytes(device.image[k:k + 2], "big") for k in (start, start + 2)]
            single = np.float32(from_words(words, DataType.FLOAT32, order))   # the register map's own decoder
            computed = source.computed(index, var.first.quantity)
            served[index, var.name] = server.value(index, var)
            rule[index, var.name] = computed if computed is not None and np.float32(computed) == single \
                else float(str(single))
    return served, rule


def test_a_float32_variable_is_the_ticks_double_or_the_written_number_in_either_word_order():
    """The float32 registers (pv, op, sp, mv, time) are read straight from the image's bytes: the same values in
    both word orders, the tick's double where the image still holds it, the number written where a write changed
    the image since the tick."""
    served_abcd, rule_abcd = _float32_served("ABCD", 61.3)
    served_cdab, rule_cdab = _float32_served("CDAB", 61.3)
    assert served_abcd == rule_abcd and served_cdab == rule_cdab
    assert served_abcd == served_cdab
    assert served_abcd[1, "op"] == 61.3                                  # written: not 61.29999923706055
    pv = served_abcd[0, "pv"]
    assert pv != float(np.float32(pv))                                   # the tick's double, not the float32's
    time = served_abcd[0, "time"]                                        # 5 ticks of 0.1 s: no float32 artefact
    assert 0.3 < time < 0.6 and time == round(time, 9) and time != float(np.float32(time))
