"""docs/testing.md's examples are test files a user copies into a fresh project: they run here as they would there
(in a scratch folder, with no ini file and no conftest, pytest-asyncio in its default strict mode)."""

from __future__ import annotations

import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[2] / "docs" / "testing.md"
FILE = re.compile(r"```python\n# file: (\S+)\n(.*?)```", re.S)
TEST = re.compile(r"^(?:async )?def test_", re.M)


def examples() -> dict[str, str]:
    """The Python blocks of docs/testing.md that name their file (``# file: test_x.py`` on the first line)."""
    return {name: code for name, code in FILE.findall(DOC.read_text(encoding="utf-8"))}


def test_the_guide_has_the_three_examples_the_kit_promises():
    assert {"test_pi_loop.py", "test_poller.py", "test_valve_watchdog.py"} <= set(examples())


def test_the_guides_examples_pass_in_a_fresh_project(pytester, run_pytest):
    found = examples()
    for name, code in found.items():
        (pytester.path / name).write_text(code, encoding="utf-8")
    tests = sum(len(TEST.findall(code)) for code in found.values())
    result = run_pytest("-q")
    result.assert_outcomes(passed=tests)
