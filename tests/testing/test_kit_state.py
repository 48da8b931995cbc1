"""``Emulator.state`` shows the status bits by name; ``inject`` takes the fault names scenario files use."""

from __future__ import annotations

import pytest
from pymodbus.exceptions import ModbusIOException

from valve_emulator.device.malfunctions import KINDS, Kind
from valve_emulator.device.registers import CommFault, Status
from valve_emulator.testing import Emulator


@pytest.fixture(scope="module")
def emu():
    with Emulator() as emu:
        yield emu


def test_state_names_every_status_bit_and_agrees_with_the_status_word(emu):
    emu.inject("clear")
    emu.advance(1.0)
    state = emu.state(0)
    assert {b.name.lower() for b in Status} <= set(state)
    for bit in Status:
        assert state[bit.name.lower()] is bool(state["status"] & bit)
    assert state["seized"] is False and state["controller"] is False      # the default device: no controller


def test_a_seized_valve_shows_as_seized(emu):
    emu.inject("seize")
    emu.advance(0.5)
    assert emu.state(0)["seized"] is True and emu.state(0)["moving"] is False
    emu.inject("release")
    emu.advance(0.5)
    assert emu.state(0)["seized"] is False


@pytest.mark.parametrize("fault", [f.name.lower() for f in CommFault])
def test_inject_takes_a_comm_fault_by_the_name_a_scenario_file_uses(emu, fault):
    applied = emu.inject("comm", fault=fault)
    assert applied["fault"] == CommFault[fault.upper()]
    emu.inject("clear")


def test_no_response_by_name_makes_the_client_time_out(emu):
    emu.inject("comm", fault="no_response")
    try:
        with emu.client(timeout=0.3) as plc, pytest.raises(ModbusIOException, match="No response received"):
            plc.read_holding_registers(0, count=1, device_id=1)
    finally:
        emu.inject("clear")
    with emu.client() as plc:
        assert not plc.read_holding_registers(0, count=1, device_id=1).isError()


def test_inject_knows_every_kind_of_the_one_list(emu):
    assert set(KINDS) == set(Kind)
    with pytest.raises(ValueError, match="one of " + ", ".join(k.value for k in Kind)):
        emu.inject("jam")
