"""Shared by the OPC UA and Modbus/TLS tests: a device with one controlled loop and one open loop."""

import pytest

from valve_emulator.config import server_from_mapping

from .modes import MODES

DEVICE = {
    "device": {"tick": 0.1},
    "loops": [
        {"unit": 1, "name": "FIC101", "valve": {"S": 5.0, "J": 2.0},
         "plant": {"fopdt": {"gain": 2.0, "tau": 10.0, "delay": 1.0}, "pv_range": [0.0, 50.0], "units": "m3/h"},
         "controller": {"kc": 0.3, "ti": 10.0}},
        {"unit": 2, "name": "XV2", "valve": {"S": 3.0, "J": 1.0},
         "plant": {"fopdt": {"gain": 1.0, "tau": 5.0, "delay": 0.5}, "pv_range": [-10.0, 10.0]}},
    ],
}


@pytest.fixture
def config():
    return server_from_mapping(DEVICE)



@pytest.fixture(params=MODES)
def opcua_mode(request):
    """Each OPC UA test runs twice: in the device's process and in a process of its own."""
    return request.param
