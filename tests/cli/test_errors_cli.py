"""What the command line does with an error: one line and exit code 2 for an error in what the user gave, a
traceback for a bug, and ``--debug`` to see the traceback of a user error too."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from valve_emulator.cli import main as cli_main


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_a_missing_config_is_one_line_naming_the_file_and_exit_code_2(tmp_path, capsys):
    missing = tmp_path / "nope.yaml"
    assert cli_main(["simulate", str(missing), "--out", str(tmp_path / "out.csv")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line.startswith("valve-emulator simulate: error: ") and str(missing) in line
    assert not (tmp_path / "out.csv").exists()


def test_a_missing_recording_is_one_line_naming_it(tmp_path, capsys):
    missing = tmp_path / "nope.csv"
    assert cli_main(["diagnose", str(missing)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert f"error: {missing}: No such file or directory" in line


def test_an_output_folder_that_cannot_be_made_names_the_flag(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    assert cli_main(["figure5", "--out", str(blocker / "figures")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert f"error: --out {blocker / 'figures'}" in line


def test_a_port_in_use_is_one_line_naming_the_flag_and_port(capsys):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        assert cli_main(["serve", "--port", str(port)]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line.endswith(f"error: --port {port}: address already in use")


def test_a_bad_flag_value_is_one_line_naming_the_flag(tmp_path, capsys):
    assert cli_main(["prove", "--case", "no such case", "--out", str(tmp_path)]) == 2
    assert "error: --case ['no such case'] matches none of" in _one_error_line(capsys.readouterr().err)


def test_debug_shows_the_traceback_of_a_user_error_then_the_line(tmp_path, capsys):
    missing = tmp_path / "nope.yaml"
    for argv in (["--debug", "limit-cycle", str(missing)], ["limit-cycle", str(missing), "--debug"]):
        assert cli_main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("Traceback (most recent call last):") and "ConfigError" in err
        assert err.strip().splitlines()[-1].startswith("valve-emulator limit-cycle: error: ")


def test_a_bug_is_not_caught_in_process(monkeypatch):
    import valve_emulator.commands.figure5 as figure5

    def broken(args):
        return [][0]

    monkeypatch.setattr(figure5, "run", broken)
    with pytest.raises(IndexError):
        cli_main(["figure5", "--out", "unused"])


def test_a_bug_shows_its_traceback_and_exits_1_not_2(tmp_path):
    """A numpy error inside a command (here a broadcasting error) is a bug, not "error: ..." with code 2."""
    code = ("import sys, numpy as np, valve_emulator.commands.figure5 as f\n"
            "f.run = lambda args: np.zeros(3) + np.zeros(4)\n"
            "from valve_emulator.cli import main\n"
            f"sys.exit(main(['figure5', '--out', {str(tmp_path)!r}]))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    assert "Traceback (most recent call last):" in done.stderr
    assert "ValueError: operands could not be broadcast together" in done.stderr
    assert "valve-emulator figure5: error:" not in done.stderr
