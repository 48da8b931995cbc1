"""node-opcua-client (from the npm registry, installed by .ci/run into tests/opcua/node) against
``valve-emulator serve --opcua``: browse, read, write OP, a refused write, a subscription; anonymous on loopback
and Basic256Sha256 Sign&Encrypt with a user name."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from required import node_with

from valve_emulator.cli import main
from valve_emulator.opcua import hash_password

from .test_opcua_interop import start_serve, stop

NODE_DIR = Path(__file__).parent / "node"
LOOP = "Unit1.concentration_undershoot"


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
    pvs = seen["pv_notifications"]   # OP went to 61.5 % from the initial 50 %: the valve slips and PV follows
    assert len(pvs) >= 2 and len(set(pvs)) >= 2, pvs


def test_node_opcua_anonymous_on_loopback(node):
    proc, url, _ = start_serve("--opcua", "0")
    try:
        _check(run_node_client(node, url))
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]


def test_node_opcua_basic256sha256_with_a_user(node, tmp_path):
    assert main(["certs", "--opcua", str(tmp_path)]) == 0
    users = tmp_path / "users.yaml"
    users.write_text(f"users:\n  otto: {{role: operator, password: '{hash_password('run', iterations=2000)}'}}\n")
    proc, url, _ = start_serve("--opcua", "0", "--opcua-policy", "Basic256Sha256", "--opcua-cert",
                               str(tmp_path / "server.der"), "--opcua-key", str(tmp_path / "server-key.pem"),
                               "--opcua-users", str(users))
    try:
        _check(run_node_client(node, url, "--secure", "otto", "run"))
        refused = run_node_client(node, url, "--secure", "otto", "wrong")
        assert not refused["ok"]
    finally:
        err = stop(proc)
    assert "Traceback" not in err, err[-2000:]
