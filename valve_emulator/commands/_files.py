"""The files and folders a command was given: an operating-system error on one of them is the user's to fix.

A missing recording, an output folder without write permission, a full disk: :func:`user_files` turns the
:class:`OSError` into a :class:`~valve_emulator.errors.UserError` naming the flag and the file, which the
command line prints as one line (exit code 2). An ``OSError`` about any other file is left alone: it is not
something the user gave, so it shows its traceback like any other bug.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from valve_emulator.errors import UserError

__all__ = ["user_files"]


def _flag_of(filename: str | os.PathLike, files: Mapping[str, Path | None]) -> tuple[str, Path] | None:
    """The ``(flag, path)`` of ``files`` that ``filename`` is, or lies inside (a folder given by a flag)."""
    target = Path(filename).absolute()
    for flag, path in files.items():
        if path is None:
            continue
        given = Path(path).absolute()
        if target == given or given in target.parents:
            return flag, Path(path)
    return None


@contextmanager
def user_files(files: Mapping[str, Path | None]) -> Iterator[None]:
    """Run the block; an ``OSError`` on one of ``files`` (flag → path, or inside that folder) becomes a
    ``UserError`` naming the flag, the file and what went wrong. A positional argument's flag is ``""``."""
    try:
        yield
    except OSError as exc:
        if exc.filename is None or (given := _flag_of(exc.filename, files)) is None:
            raise
        flag, path = given
        where = f"{flag} {path}".lstrip()   # a positional argument's "flag" is ""
        if Path(exc.filename).absolute() != path.absolute():
            where += f": {exc.filename}"
        raise UserError(f"{where}: {exc.strerror or exc}") from exc


def check_figure(flag: str, path: Path | None) -> None:
    """Refuse a figure file whose extension matplotlib cannot write (``--plot fig.pgn``), naming the flag, before
    a command computes or writes anything. A name without an extension is written as PNG."""
    if path is None or not path.suffix:
        return
    from matplotlib.backend_bases import FigureCanvasBase

    formats = FigureCanvasBase.get_supported_filetypes()
    if path.suffix[1:].lower() not in formats:
        raise UserError(f"{flag} {path}: cannot write a {path.suffix} figure; use one of "
                        f"{', '.join('.' + f for f in sorted(formats))}")
