"""Helpers of the testing kit's own tests: running pytest on a scratch project as a user would."""

from __future__ import annotations

from importlib.metadata import entry_points

import pytest

PLUGIN = "valve_emulator.testing.plugin"


def plugin_args() -> list[str]:
    """Command-line arguments that give a pytest run the kit's plugin: none once the package's ``pytest11`` entry
    point is installed (``pip install``, what users do and ``.ci/run`` does); ``-p`` on an older install."""
    installed = any(ep.value == PLUGIN for ep in entry_points(group="pytest11"))
    return [] if installed else ["-p", PLUGIN]


@pytest.fixture
def run_pytest(pytester):
    """``run_pytest(*args)``: pytest in a subprocess (as a user runs it: in-process runs would re-import the
    compiled kernels) inside pytester's scratch folder, with the kit's plugin."""
    def run(*args: str):
        return pytester.runpytest_subprocess(*plugin_args(), "-p", "no:cacheprovider", *args, timeout=300)
    return run
