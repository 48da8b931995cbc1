"""node-opcua-client (from the npm registry, installed by .ci/run into tests/opcua/node) against
``valve-emulator serve --opcua``: browse, read, units, status, write OP, a refused write, a subscription with its
timestamps; anonymous on loopback and Basic256Sha256 Sign&Encrypt with a user name; the PV alarm's condition
(ConditionRefresh, Acknowledge)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from required import node_with

import valve_emulator
from valve_emulator.cli import main
from valve_emulator.opcua import hash_password

from .test_opcua_interop import start_serve, stop

NODE_DIR = Path(__file__).parent / "node"
LOOP = "Unit1.concentration_undershoot"
DEFAULT_DEVICE = Path(valve_emulator.__file__).parent / "data" / "default_device.yaml"
CEFACT = "http://www.opcfoundation.org/UA/units/un/cefact"


@pytest.fixture(scope="module")
def node() -> str:
    """The node binary with node-opcua-client installed in tests/opcua/node (``npm ci`` there, which
    ``.ci/run`` does)."""
    return node_with(NODE_DIR, "node-opcua-client")


def run_node_client(node: str, url: str, *args: str) -> dict:
    done = subprocess.run([node, str(NODE_DIR / "client.mjs"), url, LOOP, *args], capture_output=True, text=True,
                          timeout=120, cwd=NODE_DIR)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
    assert lines, done.stdout[-2000:] + done.stderr[-2000:]
    return json.loads(lines[-1])


def _check(seen: dict) -> None:
    assert seen["ok"], seen
    assert {"pv", "sp", "op", "mv", "S", "J", "stuck", "seized"} <= set(seen["children"])
    assert isinstance(seen["pv"], (int, float))   # JSON drops the .0 of a Double
    assert seen["write_op"] == "Good" and seen["op"] == pytest.approx(61.5)
    assert seen["write_pv"] == "BadNotWritable"
    times = seen["time_notifications"]
    assert len(times) >= 5 and times == sorted(times) and times[-1] > times[0]   # time-scale 10: ~20 s in 2 s
    # whole ticks of 0.1 s, as doubles: a float32 would be off by up to 1e-6 (1.2999999523 for 1.3)
    assert all(abs(t * 10 - round(t * 10)) < 1e-9 for t in times), times
    pvs = seen["pv_notifications"]   # OP went to 61.5 % from the initial 50 %: the valve slips and PV follows
    assert len(pvs) >= 2 and len(set(pvs)) >= 2, pvs
    # each notification is stamped with the wall-clock time of its tick (the simulated clock, 10 times faster,
    # would run ahead), sent after it and received within the publishing interval and the tick period
    for source, server, received in seen["time_stamps"]:
        assert source <= server + 1 and server <= received + 50 and received - source < 1000, seen["time_stamps"]
    assert seen["units"]["op"] == {"namespaceUri": CEFACT, "unitId": 20529, "displayName": "%"}   # P1 percent
    assert seen["units"]["time"]["unitId"] == 5457219   # SEC second


def test_node_opcua_anonymous_on_loopback(node):
    proc, url, _ = start_serve("--opcua", "0")
    try:
        seen = run_node_client(node, url)
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]
    _check(seen)
    assert seen["units"]["pv"] is None   # the default device's PV has no units: no EngineeringUnits at all


def test_node_opcua_reads_unece_pv_units_and_an_uncertain_pv_outside_its_range(node, tmp_path):
    """A loop in kg/h whose PV starts at 0, below its range 1..10: node-opcua reads the UNECE unit E93 and the
    Uncertain status OPC UA gives a value outside its EURange."""
    config = DEFAULT_DEVICE.read_text().replace("pv_range: [-10.0, 10.0]", 'pv_range: [1.0, 10.0]\n  units: "kg/h"')
    assert 'units: "kg/h"' in config
    (tmp_path / "plant.yaml").write_text(config)
    proc, url, _ = start_serve(str(tmp_path / "plant.yaml"), "--opcua", "0")
    try:
        seen = run_node_client(node, url)
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]
    _check(seen)
    assert seen["units"]["pv"] == {"namespaceUri": CEFACT, "unitId": 4536627, "displayName": "kg/h"}   # E93
    assert seen["pv"] < 1.0 and seen["pv_status"] == "UncertainEngineeringUnitsExceeded"
    assert seen["pv_statuses"][0] == "UncertainEngineeringUnitsExceeded"


def test_node_opcua_basic256sha256_with_a_user_once_its_certificate_is_trusted(node, tmp_path):
    """node-opcua makes its own application certificate: the first session is refused and the certificate
    lands in pki/rejected/certs; moved to pki/trusted/certs, the client gets in."""
    assert main(["certs", "--opcua", str(tmp_path)]) == 0
    users = tmp_path / "users.yaml"
    users.write_text(f"users:\n  otto: {{role: operator, password: '{hash_password('run', iterations=2000)}'}}\n")
    pki = tmp_path / "pki"
    proc, url, _ = start_serve("--opcua", "0", "--opcua-policy", "Basic256Sha256", "--opcua-cert",
                               str(tmp_path / "server.der"), "--opcua-key", str(tmp_path / "server-key.pem"),
                               "--opcua-users", str(users), "--opcua-pki", str(pki))
    try:
        assert not run_node_client(node, url, "--secure", "otto", "run")["ok"]
        [rejected] = (pki / "rejected" / "certs").iterdir()
        rejected.rename(pki / "trusted" / "certs" / rejected.name)
        _check(run_node_client(node, url, "--secure", "otto", "run"))
        refused = run_node_client(node, url, "--secure", "otto", "wrong")
        assert not refused["ok"]
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]
    assert "refused OPC UA session" in err and "BadCertificateUntrusted" in err


def test_node_opcua_refreshes_and_acknowledges_the_pv_alarm(node, tmp_path):
    """The default device with its PV range moved to 1..10: PV starts at 0, below the low alarm limit 1.9, so the
    alarm is raised before the client connects. node-opcua's ConditionRefresh shows it, its Acknowledge call
    acknowledges it, and the Modbus ``alarms`` register loses its not-acknowledged bit."""
    from pymodbus.client import ModbusTcpClient

    from valve_emulator.device.registers import AlarmBit, address_of

    config = DEFAULT_DEVICE.read_text().replace("pv_range: [-10.0, 10.0]", "pv_range: [1.0, 10.0]")
    (tmp_path / "plant.yaml").write_text(config)
    proc, url, port = start_serve(str(tmp_path / "plant.yaml"), "--opcua", "0")
    try:
        done = subprocess.run([node, str(NODE_DIR / "alarms.mjs"), url, "concentration_undershoot"],
                              capture_output=True, text=True, timeout=120, cwd=NODE_DIR)
        lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
        assert lines, done.stdout[-2000:] + done.stderr[-2000:]
        seen = json.loads(lines[-1])
        with ModbusTcpClient("127.0.0.1", port=port, timeout=5) as mb:
            word = mb.read_holding_registers(address_of("alarms"), count=1, device_id=1).registers[0]
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]
    assert seen["ok"], seen
    assert seen["refresh"] == "Good" and seen["acknowledge"] == "Good"
    assert seen["raised"]["message"].startswith("concentration_undershoot: PV ")
    assert "below its low limit 1.9" in seen["raised"]["message"]
    assert (seen["raised"]["active"], seen["raised"]["acked"], seen["raised"]["retain"]) == (True, False, True)
    assert seen["raised"]["conditionId"] == "ns=2;s=Unit1.concentration_undershoot.PvAlarm"
    assert (seen["acked"]["active"], seen["acked"]["acked"]) == (True, True)
    assert word == AlarmBit.PV_LOW
