"""``serve --web`` flags: clear errors before anything starts."""

import pytest

from valve_emulator.cli import main


@pytest.mark.parametrize(("argv", "words"), [
    (["--web", "0", "--host", "0.0.0.0"], "--web on --host 0.0.0.0 needs --web-token"),
    (["--web", "70000"], "--web must be a port 0..65535"),
    (["--web-token", "abcdefgh"], "need --web PORT"),
    (["--web", "0", "--backtrack", "-1"], "--backtrack must be >= 0"),
])
def test_bad_web_flags_are_clear_errors(argv, words, capsys):
    assert main(["serve", *argv]) != 0
    assert words in capsys.readouterr().err
