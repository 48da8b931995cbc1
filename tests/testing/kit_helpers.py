"""What the testing kit's tests share besides fixtures (a module of its own: every test folder has a conftest)."""

from __future__ import annotations

from importlib.metadata import entry_points

PLUGIN = "valve_emulator.testing.plugin"


def plugin_args() -> list[str]:
    """Command-line arguments that give a pytest run the kit's plugin: none once the package's ``pytest11`` entry
    point is installed (``pip install``, what users do and ``.ci/run`` does); ``-p`` on an older install."""
    installed = any(ep.value == PLUGIN for ep in entry_points(group="pytest11"))
    return [] if installed else ["-p", PLUGIN]
