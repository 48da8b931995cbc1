"""Node-RED, headless, runs the flow ``valve-emulator registers --format node-red`` exports against a served
profile: node-red-contrib-modbus (pinned in tests/nodered, installed by ``.ci/run``) reads the PV and writes the
OP in the profile's encoding (float32, low word first)."""

import asyncio
import json
import os
import shutil
import signal
from pathlib import Path

import pytest

from valve_emulator.config import load_server
from valve_emulator.device.registers import Scaling
from valve_emulator.device.registers.export import export
from valve_emulator.device.registers.mapping import register_map_of
from valve_emulator.device.server import EmulatorServer

pytestmark = pytest.mark.usefixtures("no_task_leak")

HERE = Path(__file__).resolve().parent
NODERED = HERE.parent / "nodered"
PROFILE = HERE.parents[1] / "configs" / "profiles" / "modicon_float_cdab.yaml"
OP = 37.5

SETTINGS = """module.exports = {
    uiPort: 0, uiHost: "127.0.0.1", httpAdminRoot: false, httpNodeRoot: false, flowFile: "flows.json",
    credentialSecret: false, diagnostics: {enabled: false}, telemetry: {enabled: false},
    logging: {console: {level: "warn", metrics: false, audit: false}},
};
"""


def _node_red() -> Path:
    """The pinned Node-RED of tests/nodered; missing: fail on CI (``CI`` set), skip elsewhere."""
    red = NODERED / "node_modules" / "node-red" / "red.js"
    if shutil.which("node") is None or not red.exists():
        message = "Node-RED is not installed: cd tests/nodered && npm ci"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return red


def _with_harness(flow: list[dict], out: Path) -> list[dict]:
    """The exported flow plus what a test bench adds: an inject node feeding OP to the flow's "encode op"
    node, and every decoded value written to ``out`` as a JSON line."""
    tab = next(n["id"] for n in flow if n["type"] == "tab")
    encode = next(n["id"] for n in flow if n.get("name") == "encode op")
    to_line = {"id": "bench-line", "type": "function", "z": tab, "name": "to line", "outputs": 1, "noerr": 0,
               "func": "msg.payload = JSON.stringify({topic: msg.topic, value: msg.payload});\nreturn msg;",
               "initialize": "", "finalize": "", "libs": [], "x": 620, "y": 120, "wires": [["bench-file"]]}
    to_file = {"id": "bench-file", "type": "file", "z": tab, "name": "values", "filename": str(out),
               "filenameType": "str", "appendNewline": True, "createDir": True, "overwriteFile": "false",
               "encoding": "utf8", "x": 820, "y": 120, "wires": [[]]}
    inject = {"id": "bench-op", "type": "inject", "z": tab, "name": f"op = {OP}", "props": [{"p": "payload"}],
              "repeat": "", "crontab": "", "once": True, "onceDelay": "0.5", "topic": "", "payload": str(OP),
              "payloadType": "num", "x": 120, "y": 20, "wires": [[encode]]}
    for node in flow:
        if node["type"] == "function" and node["name"].startswith("decode "):
            node["wires"] = [node["wires"][0] + ["bench-line"]]
    return [*flow, to_line, to_file, inject]


async def _stop(proc) -> str:
    if proc.returncode is None:
        proc.send_signal(signal.SIGTERM)
        try:
            await asyncio.wait_for(proc.wait(), 10)
        except TimeoutError:
            proc.kill()
            await proc.wait()
    return (await proc.stdout.read()).decode(errors="replace")


async def test_node_red_runs_the_exported_flow_reading_pv_and_writing_op(tmp_path):
    red = _node_red()
    config = load_server(PROFILE)
    async with EmulatorServer(config, time_scale=0) as srv:
        srv.device.advance(20)
        flow = json.loads(export("node-red", register_map_of(config), Scaling.from_config(config),
                                 pv_units=config.loops[0].plant.units, host="127.0.0.1", port=srv.port, unit=1))
        user = tmp_path / "user"
        user.mkdir()
        out = tmp_path / "values.jsonl"
        (user / "flows.json").write_text(json.dumps(_with_harness(flow, out)))
        (user / "settings.js").write_text(SETTINGS)
        (user / "node_modules").symlink_to(NODERED / "node_modules")
        proc = await asyncio.create_subprocess_exec(
            "node", str(red), "-u", str(user), "-s", str(user / "settings.js"), stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT)
        seen: dict[str, float] = {}
        try:
            for _ in range(150):   # up to 15 s: Node-RED starts, polls every second, writes once
                await asyncio.sleep(0.1)
                if out.exists():
                    for line in out.read_text().splitlines():
                        item = json.loads(line)
                        seen[item["topic"]] = item["value"]
                srv.device.advance(1)
                # PV and MV are separate polls, written as they come: wait for both, not only the first
                if {"pv", "mv"} <= seen.keys() and srv.device.bank.op_external[0] == pytest.approx(OP):
                    break
        finally:
            log = await _stop(proc)
        assert srv.device.bank.op_external[0] == pytest.approx(OP), log     # the flow wrote OP (float32 CDAB)
        assert "pv" in seen, log
        assert seen["pv"] == pytest.approx(srv.device.bank.pv[0], abs=1.0), seen   # decoded from float32 CDAB
        assert seen["mv"] == pytest.approx(srv.device.bank.mv[0], abs=5.0), seen
