"""Third-party parts a test drives (Debian tools, npm packages): required on CI, where ``.ci/run`` installs
them, so a missing one fails the test there (``CI`` set); elsewhere the test is skipped, naming what is missing."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest


def need(problem: str | None) -> None:
    """Fail on CI, skip elsewhere, when ``problem`` (what is missing and how to get it) is not None."""
    if problem is None:
        return
    if os.environ.get("CI"):
        pytest.fail(f"{problem} (required on CI)")
    pytest.skip(problem)


def tool(name: str, install: str) -> str:
    """The path of the program ``name``; ``install`` says how to get it."""
    path = shutil.which(name)
    need(None if path else f"{name} is not installed ({install})")
    return path


def node_with(folder: Path, package: str) -> str:
    """The node binary, with the npm ``package`` installed in ``folder`` (``npm ci`` there, as .ci/run does)."""
    path = shutil.which("node")
    need("node is not installed" if path is None else
         None if (folder / "node_modules" / package).is_dir() else
         f"{package} is not installed: run `npm ci` in {folder}")
    return path
