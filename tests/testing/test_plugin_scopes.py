"""The plugin in a user's project: module- and session-wide emulators, a marker's config path read from the test
file's folder, and a clean run that stays clean with every warning an error."""

from __future__ import annotations


def test_module_and_session_fixtures_share_one_emulator_each(pytester, run_pytest):
    pytester.makepyfile(test_first="""
        import pytest

        pytestmark = pytest.mark.valve_emulator(config={"device": {"tick": 0.5}, "loops": [
            {"unit": 7, "plant": {"num": [1.0], "den": [3.0, 1.0]}}]})
        seen = {}

        def test_one(valve_emulator_module, valve_emulator_session):
            valve_emulator_module.advance(5.0)
            valve_emulator_session.advance(1.0)
            seen["module"], seen["session"] = valve_emulator_module, valve_emulator_session
            assert valve_emulator_module.units == (7,) and valve_emulator_session.units == (1,)

        def test_two_sees_the_ticks_of_test_one(valve_emulator_module, valve_emulator_session):
            assert valve_emulator_module is seen["module"] and valve_emulator_module.ticks == 10
            assert valve_emulator_session is seen["session"]
    """, test_second="""
        import test_first

        def test_the_session_emulator_outlives_the_module(valve_emulator_session, valve_emulator_module):
            assert valve_emulator_session is test_first.seen["session"] and valve_emulator_session.ticks == 10
            assert valve_emulator_module is not test_first.seen["module"] and valve_emulator_module.units == (1,)
            assert test_first.seen["module"].server is None      # stopped after its module's last test
    """)
    result = run_pytest("-q")
    result.assert_outcomes(passed=3)


def test_a_markers_config_path_is_read_from_the_test_files_folder(pytester, run_pytest):
    folder = pytester.mkdir("loops")
    (folder / "slow.yaml").write_text("device: {tick: 0.5}\nloops:\n  - unit: 4\n"
                                      "    plant: {num: [1.0], den: [3.0, 1.0]}\n")
    (folder / "test_plant.py").write_text(
        "import pytest\n\n"
        "@pytest.mark.valve_emulator(config='slow.yaml')\n"
        "def test_the_device_next_to_this_file(valve_emulator):\n"
        "    assert valve_emulator.units == (4,) and valve_emulator.dt == 0.5\n")
    result = run_pytest("-q", "loops")       # run from the project's root, not from the test's folder
    result.assert_outcomes(passed=1)


def test_a_clean_project_runs_with_every_warning_an_error(pytester, run_pytest, monkeypatch):
    """No ini file at all, warnings errors both for pytest (-W error) and for Python itself (import time, the
    plugins' configure hooks): sync and async tests of the kit still pass, and no warning is reported."""
    monkeypatch.setenv("PYTHONWARNINGS", "error")
    for name in ("PYTEST_XDIST_WORKER", "PYTEST_XDIST_WORKER_COUNT", "PYTEST_XDIST_TESTRUNUID"):
        monkeypatch.delenv(name, raising=False)   # this suite's own xdist worker is not the clean project's
    pytester.makepyfile(test_clean="""
        import pytest

        def test_sync(valve_emulator):
            with valve_emulator.client() as plc:
                plc.write_register(0, 4000, device_id=1)
            valve_emulator.advance(1.0)
            assert valve_emulator.state(0)["op_pct"] == 40.0

        @pytest.mark.asyncio
        async def test_async(valve_emulator):
            assert await valve_emulator.advance(1.0) == 10
    """)
    result = run_pytest("-W", "error", "-rw")
    result.assert_outcomes(passed=2)
    output = result.stdout.str() + result.stderr.str()
    assert "warnings summary" not in output and "Warning:" not in output and "INTERNALERROR" not in output
