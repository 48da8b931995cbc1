"""Config loading shared by the commands that serve or describe a device."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["DEFAULT_DEVICE", "load_server_or_default"]

DEFAULT_DEVICE = "default_device.yaml"


def load_server_or_default(path: Path | None):
    """``load_server(path)``, or the embedded default device when ``path`` is None."""
    from valve_emulator.config import load_server

    if path is not None:
        return load_server(path)
    with resources.as_file(resources.files("valve_emulator.data") / DEFAULT_DEVICE) as p:
        return load_server(p)
