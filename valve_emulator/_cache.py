"""Where numba keeps the compiled kernels: a user cache directory, never inside the installed package.

numba's default (``__pycache__`` beside the source) writes into site-packages. That breaks twice: a read-only
install (system site-packages, a container's non-root user) cannot write there and compiles on every run, and
cache files left behind when pip removes the package turn the folder into a namespace package that shadows a
later editable install. So, unless the user chose a place with ``NUMBA_CACHE_DIR``, the kernels go to

* ``$XDG_CACHE_HOME/valve_emulator/numba`` (default ``~/.cache/valve_emulator/numba``) on Linux and other Unix,
* ``~/Library/Caches/valve_emulator/numba`` on macOS,
* ``%LOCALAPPDATA%\\valve_emulator\\numba`` on Windows,

or, when that cannot be created, a per-user folder in the system's temporary directory. numba names each
module's files after its full source path, so two installs (or two checkouts) never share an entry, and a file
whose source changed is recompiled.

This module is imported first by ``valve_emulator/__init__.py``, before any module that compiles.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

__all__ = ["cache_dir", "configure"]


def _user_cache_home() -> Path:
    if sys.platform == "win32":
        return Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")


def _writable(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(path, os.W_OK | os.X_OK)


def cache_dir() -> Path:
    """The folder for compiled kernels: ``NUMBA_CACHE_DIR`` when set, else the user cache (see module doc)."""
    chosen = os.environ.get("NUMBA_CACHE_DIR")
    if chosen:
        return Path(chosen)
    try:
        preferred = _user_cache_home() / "valve_emulator" / "numba"
    except RuntimeError:  # no home directory can be determined
        preferred = None
    if preferred is not None and _writable(preferred):
        return preferred
    user = os.environ.get("USER") or os.environ.get("USERNAME") or str(getattr(os, "getuid", lambda: "user")())
    return Path(tempfile.gettempdir()) / f"valve_emulator-{user}" / "numba"


def configure() -> Path:
    """Point numba's cache at :func:`cache_dir` (for numba imported before or after this call)."""
    path = cache_dir()
    os.environ.setdefault("NUMBA_CACHE_DIR", str(path))
    config = sys.modules.get("numba.core.config")
    if config is not None and not config.CACHE_DIR:
        config.CACHE_DIR = str(path)
    return path
