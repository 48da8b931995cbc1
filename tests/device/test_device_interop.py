"""Independent client implementations against the served device: pyModbusTCP and modbus-tk read the bit
tables and the holding registers and write a coil (each runs its own blocking socket code in a thread)."""

import asyncio

import pytest
from modbus_tk import defines as cst
from modbus_tk import modbus_tcp
from modbus_tk.modbus import ModbusError
from pyModbusTCP.client import ModbusClient

from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import address_of
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

OPEN_LOOP, WITH_PI = 1, 2


@pytest.fixture
def server(fake_bank_cls):
    config = server_from_mapping({"device": {"tick": 0.1}, "loops": [
        {"unit": OPEN_LOOP, "plant": {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]}},
        {"unit": WITH_PI, "plant": {"num": [1.0], "den": [1.0, 0.0], "pv_range": [-10.0, 10.0]},
         "controller": {"kc": 0.4, "ti": 2.0}},
    ]})
    return EmulatorServer(config, bank=fake_bank_cls.for_config(config), time_scale=0)


def _pymodbustcp_session(port):
    client = ModbusClient(host="127.0.0.1", port=port, unit_id=WITH_PI, timeout=2.0, auto_open=True)
    try:
        seen = {"inputs": client.read_discrete_inputs(0, 7), "coils": client.read_coils(0, 2),
                "holding": client.read_holding_registers(0, 3), "mode": client.read_holding_registers(6, 1)}
        seen["wrote"] = client.write_single_coil(0, False)
        seen["coils after"] = client.read_coils(0, 2)
        seen["mode after"] = client.read_holding_registers(6, 1)
        seen["refused"] = client.write_single_coil(1, True)        # instructor coil: not allowed
        seen["refused code"] = client.last_except
        return seen
    finally:
        client.close()


async def test_pymodbustcp_reads_bits_and_registers_and_writes_a_coil(server):
    async with server as srv:
        seen = await asyncio.to_thread(_pymodbustcp_session, srv.port)
        assert seen["inputs"] == [True, False, False, False, True, True, False]   # stuck, controller, auto
        assert seen["coils"] == [True, False] and seen["mode"] == [1]
        assert seen["holding"] == [5000, 12000, 5000]                             # op 50 %, 12 mA, mv 50 %
        assert seen["wrote"] is True
        assert seen["coils after"] == [False, False] and seen["mode after"] == [0]
        assert seen["refused"] is False and seen["refused code"] == 2             # illegal data address
        srv.device.advance(1)
        assert srv.device.bank.calls == [("auto", 1, False)]


def _modbus_tk_session(port):
    master = modbus_tcp.TcpMaster(host="127.0.0.1", port=port, timeout_in_sec=2.0)
    try:
        seen = {"inputs": master.execute(WITH_PI, cst.READ_DISCRETE_INPUTS, 0, 7),
                "coils": master.execute(OPEN_LOOP, cst.READ_COILS, 0, 2),
                "op": master.execute(OPEN_LOOP, cst.READ_HOLDING_REGISTERS, address_of("op_pct"), 2)}
        seen["wrote"] = master.execute(WITH_PI, cst.WRITE_SINGLE_COIL, 0, output_value=0)
        seen["mode"] = master.execute(WITH_PI, cst.READ_HOLDING_REGISTERS, address_of("mode"), 1)
        try:
            master.execute(OPEN_LOOP, cst.WRITE_SINGLE_COIL, 0, output_value=1)  # no controller on unit 1
        except ModbusError as exc:
            seen["refused code"] = exc.get_exception_code()
        return seen
    finally:
        master.close()


async def test_modbus_tk_reads_bits_and_registers_and_writes_a_coil(server):
    async with server as srv:
        seen = await asyncio.to_thread(_modbus_tk_session, srv.port)
        assert seen["inputs"] == (1, 0, 0, 0, 1, 1, 0)
        assert seen["coils"] == (0, 0)                                   # no controller: not in auto
        assert seen["op"] == (5000, 12000)
        assert seen["wrote"] == (0, 0) and seen["mode"] == (0,)          # FC5 response echoes address, value
        assert seen["refused code"] == 2
