"""Hostile input on every interface, at CI size: the stress of ``tests/hostile_input.py`` (which
``bench/bench_interfaces_under_attack.py`` runs at full size) against one ``valve-emulator serve`` process,
phase by phase."""

import pytest
from hostile_input import CI, run
from required import tool


@pytest.fixture(scope="module")
def figures():
    """One run of every phase at CI size: ``{phase: figures}``."""
    tool("socat", "apt-get install socat")
    return {f["phase"]: f for f in run(CI)}


def _on_schedule(f):
    assert f["tick_windows"] >= 2 and f["tick_off"] == 0, f
    assert 9.0 <= f["tick_min"] <= f["tick_max"] <= 11.0 and f["monitor_errors"] == 0, f


def test_every_bad_http_request_is_a_4xx_json_error_naming_the_field_and_changes_nothing(figures):
    f = figures["http"]
    assert f["requests"] >= 90 and f["big_bodies"] == CI.big_bodies and f["slow"] == CI.slow
    assert (f["wrong_status"], f["not_json"], f["wrong_field"]) == (0, 0, 0), f.get("unexpected")
    assert f["normal_failed"] == 0 and f["unchanged"]
    _on_schedule(f)


def test_corrupted_rtu_frames_get_no_reply_and_the_next_good_one_the_right_answer(figures):
    f = figures["rtu"]
    assert f["frames"] == CI.rtu_frames and f["good_ok"]
    assert f["answered_corrupted"] == 0 and f["good_wrong"] == 0
    assert f["good_retried"] <= f["bursts"] // 5, f   # lost silences on a busy machine, not a habit
    _on_schedule(f)


def test_broken_snapshot_files_are_refused_naming_the_file_and_time_does_not_jump(figures):
    f = figures["snapshots"]
    assert f["refused"] == f["files"] == 8 and f["wrong"] == 0, f.get("answers")
    assert f["time_jumped"] == 0 and f["unchanged"]
    _on_schedule(f)


def test_sighup_with_a_broken_config_keeps_it_names_file_line_key_and_no_request_fails(figures):
    f = figures["hup"]
    assert f["reloads"] == f["named"] == f["kept"] == 4, f.get("messages")
    assert f["clients"] == 10 and f["requests"] >= 20 and f["failed"] == 0 and f["wrong"] == 0
    assert f["good_reload"]
    _on_schedule(f)


def test_no_crash_and_normal_reads_correct_afterwards(figures):
    f = figures["after"]
    assert f["alive"] and f["crashes"] == 0
    assert f["modbus_ok"] and f["http_ok"] and f["rtu_ok"]
