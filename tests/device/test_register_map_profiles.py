"""The register-map profiles of configs/profiles, served: pymodbus, mbpoll, pyModbusTCP and modbus-tk read the
PV and write the OP in each profile's encoding, and the exports describe what is served."""

import asyncio
import csv
import io
import json
import struct
from pathlib import Path

import pytest
from asyncua import Client, ua
from mbpoll_output import mbpoll_values, run
from modbus_tk import defines as cst
from modbus_tk import modbus_tcp
from modbus_tk.modbus import ModbusError
from pymodbus import FramerType
from pymodbus.client import AsyncModbusTcpClient
from pyModbusTCP.client import ModbusClient

from valve_emulator.config import load_server
from valve_emulator.device.registers import Scaling
from valve_emulator.device.registers.export import KEPWARE_COLUMNS, export
from valve_emulator.device.registers.mapping import register_map_of
from valve_emulator.device.server import EmulatorServer
from valve_emulator.opcua import NAMESPACE, LocalSource, OpcUaServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

PROFILES = Path(__file__).resolve().parents[2] / "configs" / "profiles"
S7, MODICON, MILLIAMP = (PROFILES / f"{n}.yaml" for n in ("s7_analog", "modicon_float_cdab", "ma_4_20_counts"))


def _server(path):
    """The profile served on a free port, its clock frozen (the test runs the ticks)."""
    return EmulatorServer(load_server(path), time_scale=0)


def _float_cdab(words):
    return struct.unpack(">f", struct.pack(">HH", words[1], words[0]))[0]


def _int16(word):
    return word - 65536 if word >= 32768 else word


async def _pymodbus(srv):
    client = AsyncModbusTcpClient("127.0.0.1", port=srv.port)
    await client.connect()
    return client


async def test_s7_profile_serves_analog_counts_and_refuses_counts_outside_the_raw_range():
    async with _server(S7) as srv:
        srv.device.advance(50)
        bank = srv.device.bank
        client = await _pymodbus(srv)
        try:
            pv = (await client.read_input_registers(0, count=3, device_id=1)).registers
            assert _int16(pv[0]) == round(bank.pv[0] / 200.0 * 27648)        # 0..200 m3/h as 0..27648
            assert _int16(pv[1]) == round(bank.mv[0] / 100.0 * 27648)
            assert not (await client.write_register(0, 20736, device_id=1)).isError()   # 75 % travel
            refused = await client.write_register(0, 27649, device_id=1)
            assert refused.isError() and refused.exception_code == 3
            hole = await client.read_holding_registers(1, count=1, device_id=1)
            assert hole.isError() and hole.exception_code == 2                # nothing is placed at 40002
            bits = await client.read_discrete_inputs(0, count=2, device_id=1)
            assert bits.bits[:2] == [bool(bank.stuck[0]), False]
            coil = await client.write_coil(0, True, device_id=1)               # the instructor's coil
            assert coil.isError() and coil.exception_code == 2
        finally:
            client.close()
        srv.device.advance(1)
        assert bank.op_external[0] == pytest.approx(75.0)


async def test_modicon_profile_serves_float32_cdab_and_takes_a_float_op():
    async with _server(MODICON) as srv:
        srv.device.advance(20)
        bank = srv.device.bank
        client = await _pymodbus(srv)
        try:
            words = (await client.read_input_registers(0, count=13, device_id=1)).registers
            assert _float_cdab(words[0:2]) == pytest.approx(bank.pv[0], rel=1e-6)
            assert _float_cdab(words[2:4]) == pytest.approx(bank.mv[0], rel=1e-6)
            time = struct.unpack(">d", struct.pack(">4H", *words[6:10][::-1]))[0]    # float64, low word first
            assert time == bank.sample_time
            assert words[10] + (words[11] << 16) == srv.device.ticks                  # uint32 CDAB
            high, low = struct.unpack(">HH", struct.pack(">f", 62.5))
            assert not (await client.write_registers(0, [low, high], device_id=1)).isError()
            op_ma = (await client.read_holding_registers(2, count=1, device_id=1)).registers[0]
            assert op_ma == 14000                                              # the write shows at once, in mA
            half = await client.write_register(0, low, device_id=1)
            assert half.isError() and half.exception_code == 2                 # a float is written whole
        finally:
            client.close()
        srv.device.advance(1)
        assert bank.op_external[0] == pytest.approx(62.5)


async def test_milliamp_profile_serves_four_to_twenty_counts():
    async with _server(MILLIAMP) as srv:
        srv.device.advance(30)
        bank = srv.device.bank
        client = await _pymodbus(srv)
        try:
            pv = (await client.read_input_registers(200, count=1, device_id=1)).registers
            mv = (await client.read_input_registers(202, count=1, device_id=1)).registers
            words = (await client.read_input_registers(204, count=2, device_id=1)).registers
            assert pv[0] == round(6400 + bank.pv[0] / 10.0 * 25600)           # 0..10 bar as 4..20 mA
            assert mv[0] == round(6400 + bank.mv[0] / 100.0 * 25600)
            assert struct.unpack(">f", struct.pack(">HH", *words))[0] == pytest.approx(bank.pv[0], rel=1e-6)
            gap = await client.read_input_registers(200, count=3, device_id=1)
            assert gap.isError() and gap.exception_code == 2                   # 30202 is not a tag's
            assert not (await client.write_register(100, 12800, device_id=1)).isError()   # 8 mA: 25 %
            below = await client.write_register(100, 6399, device_id=1)
            assert below.isError() and below.exception_code == 3
        finally:
            client.close()
        srv.device.advance(1)
        assert bank.op_external[0] == pytest.approx(25.0)


async def test_rtu_framing_answers_through_the_configured_map_too():
    """Every Modbus adapter reads through the served map: RTU frames over TCP here."""
    async with EmulatorServer(load_server(S7), time_scale=0, framer="rtu") as srv:
        srv.device.advance(50)
        client = AsyncModbusTcpClient("127.0.0.1", port=srv.port, framer=FramerType.RTU, timeout=2, retries=0)
        await client.connect()
        try:
            pv = (await client.read_input_registers(0, count=1, device_id=1)).registers
            assert _int16(pv[0]) == round(srv.device.bank.pv[0] / 200.0 * 27648)
            standard = await client.read_holding_registers(4, count=1, device_id=1)   # the standard pv's place
            assert standard.isError() and standard.exception_code == 2
        finally:
            client.close()


async def test_opc_ua_keeps_its_node_names_and_its_writes_show_in_the_configured_map():
    """OPC UA is not a register interface: its nodes are the loop's quantities whatever map Modbus serves, and
    an OP written there reads back over Modbus in the profile's counts at once."""
    config = load_server(S7)
    async with _server(S7) as srv, OpcUaServer(LocalSource(srv.device), loops=config.loops, port=0) as opc:
        srv.device.advance(10)
        async with Client(opc.url) as ua_client:
            ns = await ua_client.get_namespace_index(NAMESPACE)
            loop = await ua_client.nodes.objects.get_child([f"{ns}:ValveEmulator", f"{ns}:Unit1",
                                                           f"{ns}:s7_flow_loop"])
            await (await loop.get_child(f"{ns}:op")).write_value(ua.DataValue(ua.Variant(40.0, ua.VariantType.Double)))
            pv = await (await loop.get_child(f"{ns}:pv")).read_value()
        client = await _pymodbus(srv)
        try:
            assert (await client.read_holding_registers(0, count=1, device_id=1)).registers == [11059]   # 40 %
            counts = (await client.read_input_registers(0, count=1, device_id=1)).registers[0]
        finally:
            client.close()
        assert pv == pytest.approx(_int16(counts) / 27648 * 200.0, abs=200.0 / 27648)


# --- third-party clients ---------------------------------------------------------------------------------------

async def test_mbpoll_reads_pv_and_writes_op_of_the_modicon_profile_with_its_references(mbpoll):
    """mbpoll's defaults are the Modicon conventions: one-based references and floats low word first."""
    async with _server(MODICON) as srv:
        srv.device.advance(20)
        base = [mbpoll, "-m", "tcp", "-p", str(srv.port), "-a", "1", "-1", "-o", "2"]
        rc, out = await run(*base, "-r", "1", "-t", "3:float", "127.0.0.1")          # 30001
        assert rc == 0, out
        assert float(mbpoll_values(out)[1]) == pytest.approx(srv.device.bank.pv[0], rel=1e-5)
        rc, out = await run(*base, "-r", "1", "-t", "4:float", "127.0.0.1", "33.25")  # 40001
        assert rc == 0, out
        srv.device.advance(1)
        assert srv.device.bank.op_external[0] == pytest.approx(33.25)


def _pymodbustcp_session(port):
    client = ModbusClient(host="127.0.0.1", port=port, unit_id=1, timeout=2.0, auto_open=True)
    try:
        return {"pv": client.read_input_registers(0, 1), "wrote": client.write_single_register(0, 13824),
                "refused": client.write_single_register(0, 30000), "code": client.last_except}
    finally:
        client.close()


async def test_pymodbustcp_reads_and_writes_the_s7_profile_counts():
    async with _server(S7) as srv:
        srv.device.advance(50)
        seen = await asyncio.to_thread(_pymodbustcp_session, srv.port)
        assert _int16(seen["pv"][0]) == round(srv.device.bank.pv[0] / 200.0 * 27648)
        assert seen["wrote"] is True and seen["refused"] is False and seen["code"] == 3
        srv.device.advance(1)
        assert srv.device.bank.op_external[0] == pytest.approx(50.0)


def _modbus_tk_session(port):
    master = modbus_tcp.TcpMaster(host="127.0.0.1", port=port, timeout_in_sec=2.0)
    try:
        seen = {"pv": master.execute(1, cst.READ_INPUT_REGISTERS, 200, 1),
                "wrote": master.execute(1, cst.WRITE_SINGLE_REGISTER, 100, output_value=32000)}
        try:
            master.execute(1, cst.READ_INPUT_REGISTERS, 199, 2)
        except ModbusError as exc:
            seen["hole"] = exc.get_exception_code()
        return seen
    finally:
        master.close()


async def test_modbus_tk_reads_and_writes_the_milliamp_profile_counts():
    async with _server(MILLIAMP) as srv:
        srv.device.advance(30)
        seen = await asyncio.to_thread(_modbus_tk_session, srv.port)
        assert seen["pv"][0] == round(6400 + srv.device.bank.pv[0] / 10.0 * 25600)
        assert seen["wrote"] == (100, 32000) and seen["hole"] == 2
        srv.device.advance(1)
        assert srv.device.bank.op_external[0] == pytest.approx(100.0)


# --- exports of what is served ---------------------------------------------------------------------------------

def _export(path, fmt, **kw):
    cfg = load_server(path)
    return export(fmt, register_map_of(cfg), Scaling.from_config(cfg), pv_units=cfg.loops[0].plant.units, **kw)


def test_kepware_csv_has_the_tag_import_columns_and_the_profile_tags():
    rows = list(csv.reader(io.StringIO(_export(S7, "kepware"))))
    assert tuple(rows[0]) == KEPWARE_COLUMNS
    tags = {r[0]: dict(zip(KEPWARE_COLUMNS, r)) for r in rows[1:]}
    assert tags["op"]["Address"] == "400001" and tags["op"]["Data Type"] == "Short"
    assert tags["op"]["Client Access"] == "R/W" and tags["pv"]["Client Access"] == "RO"
    assert (tags["pv"]["Scaling"], tags["pv"]["Raw Low"], tags["pv"]["Raw High"], tags["pv"]["Scaled Low"],
            tags["pv"]["Scaled High"], tags["pv"]["Eng Units"]) == ("Linear", "0", "27648", "0", "200", "m3/h")
    assert tags["stuck"]["Address"] == "100001" and tags["stuck"]["Data Type"] == "Boolean"
    assert tags["seized"]["Address"] == "000001" and tags["seized_discrete_input"]["Address"] == "100002"


def test_ignition_export_addresses_each_tag_with_the_modbus_driver_designators():
    folder = json.loads(_export(MODICON, "ignition", device="plc1"))
    paths = {t["name"]: t for t in folder["tags"]}
    assert paths["op"]["opcItemPath"] == "ns=1;s=[plc1]HRF1" and paths["op"]["accessRights"] == "Read_Write"
    assert paths["time"]["opcItemPath"] == "ns=1;s=[plc1]IRD7" and paths["time"]["dataType"] == "Float8"
    assert paths["tick"]["opcItemPath"] == "ns=1;s=[plc1]IRUI11"
    assert "Reverse Word Order on" in paths["pv"]["documentation"]
    op_ma = paths["op_ma"]
    assert (op_ma["scaleMode"], op_ma["rawLow"], op_ma["rawHigh"], op_ma["scaledLow"], op_ma["scaledHigh"]) == (
        "Linear", 4000.0, 20000.0, 4.0, 20.0)                                   # mA × 1000


def test_node_red_export_reads_every_tag_and_writes_the_writable_ones():
    flow = json.loads(_export(MILLIAMP, "node-red", host="10.0.0.5", port=1502, unit=7))
    client = next(n for n in flow if n["type"] == "modbus-client")
    assert (client["tcpHost"], client["tcpPort"], client["unit_id"]) == ("10.0.0.5", "1502", "7")
    reads = {n["topic"]: n for n in flow if n["type"] == "modbus-read"}
    assert set(reads) == {"op", "pv", "mv", "pv_f32"}
    assert (reads["pv"]["dataType"], reads["pv"]["adr"], reads["pv"]["quantity"]) == ("InputRegister", "200", "1")
    assert reads["pv_f32"]["quantity"] == "2" and all(n["server"] == client["id"] for n in reads.values())
    writes = [n for n in flow if n["type"] == "modbus-write"]
    assert [(w["name"], w["dataType"], w["adr"]) for w in writes] == [("write op", "HoldingRegister", "100")]


def test_the_registers_command_exports_a_profile_and_refuses_a_unit_it_does_not_have(capsys):
    from valve_emulator.cli import main as cli_main

    assert cli_main(["registers", str(S7), "--format", "kepware"]) == 0
    assert capsys.readouterr().out.splitlines()[1].startswith("op,400001,Short,1,R/W,")
    assert cli_main(["registers", str(S7)]) == 0
    assert "Not served by this map (no address in device.register_map): op_pct," in capsys.readouterr().out
    assert cli_main(["registers", str(S7), "--format", "node-red", "--unit", "9"]) == 2
    assert "--unit 9: the config has no loop on unit 9" in capsys.readouterr().err
