"""The clients as ``valve-emulator`` sub-commands: ``plc``, ``record``, ``monitor`` and ``scenario`` take the
client's own flags (the same set as ``python -m valve_emulator.clients.NAME``), run the client under the
sub-command's name, and stay out of the way of the other commands (nothing of them is imported then)."""

from __future__ import annotations

import asyncio
import re
import socket
import subprocess
import sys

import numpy as np
import pytest

from valve_emulator.cli import main as cli_main
from valve_emulator.clients import monitor, pi_controller, recorder, scenario
from valve_emulator.config import server_from_mapping
from valve_emulator.device.server import EmulatorServer
from valve_emulator.recordings.recording import read_csv

pytestmark = pytest.mark.usefixtures("no_task_leak")

COMMANDS = {  # sub-command: (client module, flags its help must name)
    "plc": (pi_controller, ("--config", "--kc", "--ti", "--td", "--scan", "--time-scale", "--sp-register",
                            "--device-time", "--op-limits", "--word-order")),
    "record": (recorder, ("--out", "--period", "--step", "--until", "--fsync", "--extra", "--no-extras", "--time")),
    "monitor": (monitor, ("--once", "--plain", "--pv-range", "--width", "--rows", "--period", "--host")),
    "scenario": (scenario, ("--check", "--attach", "--time-scale", "--record", "--record-step", "--port")),
}
LOOP = {"valve": {"S": 2.0, "J": 1.0}, "plant": {"num": [3.0], "den": [10.0, 1.0], "pv_range": [-10.0, 10.0]},
        "controller": {"kc": 0.2, "ti": 10.0, "sp": 0.0, "sp_steps": [[1.0, 1.0]]}}


def config():
    return server_from_mapping({"device": {"tick": 0.1}, "loops": [{"unit": 1, **LOOP}]})


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def long_flags(text: str) -> set[str]:
    return set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", text))


@pytest.mark.parametrize("command", COMMANDS)
def test_sub_command_help_names_the_clients_own_flags(command, capsys):
    module, flags = COMMANDS[command]
    with pytest.raises(SystemExit) as exc:
        cli_main([command, "--help"])
    out = capsys.readouterr().out
    assert exc.value.code == 0 and out.startswith(f"usage: valve-emulator {command} ")
    assert set(flags) <= long_flags(out)
    own = long_flags(out) - {"--debug"}   # --debug is the command line's (tracebacks of user errors), not the client's
    assert own == long_flags(module.build_parser().format_help())   # one set of flags, not a copy


@pytest.mark.slow
def test_sub_commands_run_from_the_entry_point_and_the_others_do_not_load_the_clients():
    for command in COMMANDS:
        done = subprocess.run([sys.executable, "-m", "valve_emulator", command, "--help"], capture_output=True,
                              text=True, timeout=120, check=False)
        assert done.returncode == 0 and f"usage: valve-emulator {command}" in done.stdout, done.stderr
    probe = ("import sys\nfrom valve_emulator.cli import main\n"
             "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
             "print(sorted(m for m in sys.modules if m.startswith(('valve_emulator.clients', 'pymodbus'))))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0 and done.stdout.splitlines()[-1] == "[]", done.stdout + done.stderr


def test_sub_commands_report_errors_under_their_own_name(tmp_path, capsys):
    port = free_port()
    argv = ["record", "--out", str(tmp_path / "never.csv"), "--port", str(port), "--timeout", "0.5", "--quiet"]
    assert cli_main(argv) == 1
    assert f"valve-emulator record: error: no Modbus TCP server at 127.0.0.1:{port}" in capsys.readouterr().err
    assert not (tmp_path / "never.csv").exists()
    assert cli_main(["plc", "--kc", "-1"]) == 2
    assert "valve-emulator plc: error: kc must be a number > 0, got -1.0" in capsys.readouterr().err
    assert cli_main(["monitor", "--width", "3"]) == 2
    assert "valve-emulator monitor: error: --width must be >= 10" in capsys.readouterr().err


async def test_record_and_monitor_sub_commands_read_a_running_emulator(tmp_path, capsys):
    out = tmp_path / "rec.csv"
    async with EmulatorServer(config(), time_scale=10.0) as srv:
        port = str(srv.port)
        # A generous per-request timeout: on a fresh checkout the emulator's first ticks compile its kernels
        # in this same event loop (a row or two of the first second then comes late), and what is tested here is
        # the sub-commands, not the latency: 16 steps, of which 80 % must be on the grid. Time scale 10 (a 10 ms
        # tick): at 20 a row came off the grid whenever a poll was 5 ms late, which a machine busy with the
        # other half of the suite sometimes is.
        assert await asyncio.to_thread(cli_main, ["record", "--port", port, "--out", str(out), "--step", "0.5",
                                                  "--period", "0.025", "--until", "8", "--quiet",
                                                  "--timeout", "20"]) == 0
        assert await asyncio.to_thread(cli_main, ["monitor", "--port", port, "--once", "--plain",
                                                  "--timeout", "20"]) == 0
    rec = read_csv(out)
    assert rec.columns[:5] == ("t", "sp", "op", "mv", "pv") and rec.t[-1] >= 8.0
    assert np.mean(np.abs(np.diff(rec.t) - 0.5) < 1e-6) >= 0.8        # on the device's time grid
    assert f"valve monitor -- 127.0.0.1:{port} unit 1" in capsys.readouterr().out
