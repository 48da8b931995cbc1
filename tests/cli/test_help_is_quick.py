"""``valve-emulator --help`` lists the commands without loading what they run: no numba kernels, no device, no
diagnosis (each is imported by the command that needs it; ``--help`` took 1.5 s when ``serve`` imported the device
at the top of its module, 0.3 s since — measured 2026-11-28)."""

from __future__ import annotations

import subprocess
import sys

HEAVY = ("numba", "scipy", "valve_emulator.device", "valve_emulator.physics", "valve_emulator.diagnosis",
         "valve_emulator.simulation", "valve_emulator.opcua", "pymodbus", "asyncua")


def test_the_command_list_loads_no_command_s_machinery():
    probe = ("import sys\nfrom valve_emulator.cli import main\n"
             "try:\n    main(['--help'])\nexcept SystemExit as exc:\n    assert exc.code == 0\n"
             f"print(sorted({{m.split('.')[0] if m.split('.')[0] != 'valve_emulator' else '.'.join(m.split('.')[:2])"
             f" for m in sys.modules}} & set({HEAVY!r})))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert "usage: valve-emulator" in done.stdout and "serve" in done.stdout
    assert done.stdout.splitlines()[-1] == "[]", done.stdout.splitlines()[-1]
