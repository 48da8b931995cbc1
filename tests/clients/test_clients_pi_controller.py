"""The soft PLC: any addresses and word order, settings from flags and YAML, a clean stop that leaves OP."""

from __future__ import annotations

import asyncio
import re
import signal
import sys
import time

import pytest

from valve_emulator.clients.pi_controller import (
    ControllerSettings,
    build_parser,
    main,
    run_controller,
    settings_from_args,
)
from valve_emulator.config import server_from_mapping
from valve_emulator.device.registers import address_of
from valve_emulator.device.server import EmulatorServer
from valve_emulator.errors import UserError
from valve_emulator.physics.controller import PID

pytestmark = pytest.mark.usefixtures("no_task_leak")

LEVEL = {"plant": {"num": [1.0], "den": [1.0, 0.0], "pv_range": [-10.0, 10.0]}}   # 1/s, no controller


def level(**device):
    return server_from_mapping({"device": {"tick": 0.1, **device}, "loops": [{"unit": 2, **LEVEL}]})


async def test_non_default_addresses_and_word_order_close_the_loop():
    """PV as float32 from the input table, OP written as a 4-20 mA current (µA), CDAB word order, unit 2:
    with a healthy valve the PI brings PV to the set point, and the valve follows the written current."""
    PID(kc=1.0, ti=1.0, dt=1.0)(0.0, 0.0)   # load the compiled kernel before the shared event loop runs
    scale = 40.0
    async with EmulatorServer(level(word_order="CDAB"), time_scale=scale) as srv:
        stop = asyncio.Event()
        settings = ControllerSettings(port=srv.port, unit=2, word_order="CDAB", pv="input:24:float32",
                                      op="holding:1:uint16:160:4000", kc=0.4, ti=2.0, sp=1.0, scan=0.1 / scale,
                                      time_scale=scale)
        plc = asyncio.create_task(run_controller(settings, stop=stop))
        await srv.device.wait_for_tick(600)                       # 60 simulated seconds
        stop.set()
        summary = await plc
        bank = srv.device.bank
        assert summary.errors == 0 and summary.scans > 300
        assert bank.pv[0] == pytest.approx(1.0, abs=0.02)         # PV at the set point
        assert bank.op_external[0] == pytest.approx(summary.op, abs=0.01)   # 1 µA = 1/160 %
        assert srv.device.image[2 * address_of("op_ma"):][:2] != bytes(2)


def test_settings_merge_defaults_file_and_flags(tmp_path):
    f = tmp_path / "plc.yaml"
    f.write_text("port: 1502\nkc: 0.3\nti: 12\nop_limits: [10, 90]\npv: input:24:float32\naction: direct\n")
    s = settings_from_args(build_parser().parse_args(["--config", str(f), "--kc", "0.5", "--ti", "0"]))
    assert (s.port, s.kc, s.ti, s.op_limits, s.pv, s.action) == (1502, 0.5, None, (10, 90), "input:24:float32",
                                                                 "direct")
    assert (s.host, s.unit, s.op, s.scan) == ("127.0.0.1", 1, "op_pct", 0.1)   # defaults fit the emulator
    assert s.dt == pytest.approx(0.1)


@pytest.mark.parametrize("text, flags, message", [
    ("gain: 3\n", [], r"plc\.yaml: unknown key 'gain'"),
    ("kc: fast\n", [], r"plc\.yaml: kc must be a number"),
    ("", ["--op", "input:3"], r"op must be a holding register"),
    ("", ["--pv", "coils:3"], r"pv: 'coils:3' is neither a register"),
    ("", ["--sp", "1", "--sp-register", "sp_f32"], r"either sp .* or sp-register"),
    ("", ["--op-limits", "90", "10"], r"op-limits must be LO HI with LO < HI"),
])
def test_bad_settings_name_the_setting(tmp_path, capsys, text, flags, message):
    f = tmp_path / "plc.yaml"
    f.write_text(text)
    with pytest.raises(UserError, match=message):
        settings_from_args(build_parser().parse_args(["--config", str(f), *flags]))
    assert main(["--config", str(f), *flags]) == 2
    assert "pi_controller: error:" in capsys.readouterr().err


async def test_ctrl_c_stops_the_plc_and_leaves_op_where_it_was():
    """The PLC as a real process: SIGINT ends it with exit code 0 and no further write, so OP stays."""
    async with EmulatorServer(level(), time_scale=20.0) as srv:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "valve_emulator.clients.pi_controller", "--port", str(srv.port), "--unit", "2",
            "--scan", "0.005", "--time-scale", "20", "--kc", "0.4", "--ti", "2", "--sp", "2.0",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        bank = srv.device.bank
        try:
            # bounded in wall time, not ticks: on a loaded machine the PLC's interpreter may take seconds to
            # import, and a SIGINT before its first write would test the import, not the PLC
            deadline = time.monotonic() + 60.0
            while time.monotonic() < deadline:
                await srv.device.wait_for_tick(srv.device.ticks + 1)
                if bank.op_external[0] != 50.0:                   # the PLC is writing
                    break
            assert bank.op_external[0] != 50.0, "the PLC never wrote OP"
            await srv.device.wait_for_tick(srv.device.ticks + 20)
            proc.send_signal(signal.SIGINT)
            _, err = await asyncio.wait_for(proc.communicate(), timeout=20)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        assert proc.returncode == 0, err.decode()
        op_at_stop = bank.op_external[0]
        reported = float(re.search(r"OP left at ([-\d.]+) %", err.decode()).group(1))
        assert op_at_stop != 50.0 and reported == pytest.approx(op_at_stop, abs=0.006)   # op_pct: 0.01 %
        await srv.device.wait_for_tick(srv.device.ticks + 20)
        assert bank.op_external[0] == op_at_stop
