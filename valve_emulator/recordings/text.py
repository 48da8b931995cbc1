"""The one text parser of every recording reader: bytes → text → lines → cells.

The standard CSV (:mod:`~valve_emulator.recordings.recording`), the DCS export (:mod:`~valve_emulator.recordings.dcs`)
and generic delimited text (:mod:`~valve_emulator.recordings.delimited`) all go through these steps; the numbers
and times in the cells are read by :class:`~valve_emulator.recordings.table.Table`.

Everything here is strict on purpose: bad input raises :class:`~valve_emulator.recordings.errors.ReaderError`
naming the file and the line (1-based, as an editor counts) and returns nothing.

Lines end at ``\\n``, ``\\r\\n`` or ``\\r`` and nowhere else (``str.splitlines`` would also split at a form feed
or U+2028 inside a cell). Cells are split as CSV does: a cell in double quotes may hold the delimiter.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from operator import methodcaller
from typing import Final

from valve_emulator.recordings.errors import ReaderError

__all__ = [
    "DELIMITERS",
    "located",
    "decode",
    "is_utf8",
    "split_lines",
    "split_terminated",
    "split_cells",
    "split_rows",
    "split_columns",
    "sniff_delimiter",
]

#: Delimiters tried by :func:`sniff_delimiter`, in order of preference when several fit.
DELIMITERS: Final = ("\t", ";", ",", "|")


def located(source: str, what: str, *, line: int | None = None, column: str | None = None,
            number: int | None = None) -> ReaderError:
    """The error ``source: line L, column 'name' (k): what`` carrying ``source``, ``line`` and ``column``.

    ``number`` is the column's 1-based position; without a name the column is given by its number alone.
    """
    where = source
    if line is not None:
        where += f": line {line}"
    if column is not None:
        where += f", column {column!r}" + (f" ({number})" if number is not None else "")
    elif number is not None:
        where += f", column {number}"
    return ReaderError(f"{where}: {what}", source=source, line=line, column=column)


def is_utf8(encoding: str) -> bool:
    """True for every spelling of UTF-8 (``utf-8``, ``UTF8``, ``utf_8``)."""
    return encoding.lower().replace("-", "").replace("_", "") == "utf8"


def decode(data: bytes, source: str, encoding: str = "utf-8", *, other_encodings: bool = True) -> str:
    """Decode a whole file strictly; a byte-order mark is dropped.

    A file that is not valid in ``encoding`` is refused with the byte offset and line of the first bad byte.
    When the bytes before it already held valid non-ASCII UTF-8 text the file mixes encodings (typically a UTF-8
    export with rows pasted from a GBK or Latin-1 editor); the message says so, because no single ``encoding``
    can then read it. Otherwise, with ``other_encodings`` (the caller accepts an ``encoding=`` argument), the
    message suggests passing one.
    """
    try:
        text = data.decode(encoding)
    except LookupError:
        raise ReaderError(f"{source}: unknown text encoding {encoding!r}", source=source) from None
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        bad = data[exc.start:exc.start + 4].hex(" ")
        utf8 = is_utf8(encoding)
        name = "UTF-8" if utf8 else encoding
        what = (f"not {name} text at byte offset {exc.start} (bytes {bad}: {exc.reason}); expected the whole "
                f"file in {name}")
        if utf8:
            # Whole earlier lines that decode to non-ASCII text mean the file started out as UTF-8; a stray
            # pair of bytes on the failing line itself proves nothing (a GBK pair can look like UTF-8).
            head = data[:data.rfind(b"\n", 0, exc.start) + 1]
            if any(b > 0x7F for b in head):
                what += ("; the lines before it are UTF-8 with non-ASCII characters, so the file mixes "
                         "encodings (re-export it in one encoding)")
            elif other_encodings:
                what += " (pass encoding=... if the whole file is in another encoding, e.g. 'gb18030')"
        raise located(source, what, line=line) from None
    return text.removeprefix("\ufeff")


def split_terminated(text: str, source: str) -> tuple[list[str], str | None]:
    """``(lines, unterminated)``: the lines that end with a line end, and a last line that does not, if any.

    A file that does not end with a line end may have been cut short by a writer that was killed; the caller
    decides whether to keep its last line. Blank lines at the very end (an editor's extra newline) are dropped
    when nothing follows them; a blank unterminated rest counts as none. A single line without a line end is
    returned as a complete line (a header alone). An empty or all-blank text is an error.
    """
    if not text.strip():
        raise ReaderError(f"{source}: line 1: the file is empty", source=source, line=1)
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    rest = lines.pop()  # "" when the text ends with a line end
    if not rest.strip():
        rest = ""
    if not lines:
        return [rest], None
    if not rest:
        while not lines[-1].strip():
            lines.pop()
    return lines, (rest or None)


def split_lines(text: str, source: str) -> list[str]:
    """All lines without terminators, an unterminated last line included; trailing blank lines dropped."""
    lines, rest = split_terminated(text, source)
    return lines if rest is None else lines + [rest]


def split_cells(line: str, delimiter: str) -> list[str]:
    """Cells of one line, quotes handled as in CSV, surrounding spaces stripped (``[""]`` for a blank line)."""
    return [c.strip() for c in split_rows([line], delimiter)[0]]


def split_rows(lines: Sequence[str], delimiter: str) -> list[list[str]]:
    """Cells of many lines, not stripped (:class:`~valve_emulator.recordings.table.Table` strips what it reads).

    Each line is one row: a quote left open does not run on into the next line (the CSV parser would join
    them, and every later line number would be off). Without a double quote in the text a cell cannot hold
    the delimiter, and a plain split gives what the CSV parser would, faster.
    """
    if any('"' in line for line in lines):
        return [next(csv.reader([line], delimiter=delimiter)) or [""] for line in lines]
    return [line.split(delimiter) for line in lines]


def split_columns(lines: Sequence[str], delimiter: str) -> list[list[str]] | None:
    """Cells of many lines by column (not stripped), or ``None`` unless every line has as many cells.

    The fast path for long, regular files: one join and one split of the whole text instead of a list per line
    (several times faster on long recordings). ``None`` too when a double quote appears (use :func:`split_rows`).
    """
    joined = delimiter.join(lines)
    if not lines or '"' in joined:
        return None
    counts = list(map(methodcaller("count", delimiter), lines))
    if counts.count(counts[0]) != len(counts):
        return None
    width = counts[0] + 1
    flat = joined.split(delimiter)
    return [flat[j::width] for j in range(width)]


def sniff_delimiter(lines: Sequence[str], *, decimal: str = ".") -> str | None:
    """The delimiter that splits the first lines into the same number (≥ 2) of cells, or ``None``.

    Up to 20 non-blank lines are looked at. ``,`` is not considered with a decimal comma. Among the delimiters
    that fit, the one giving the most columns wins (ties: the order of :data:`DELIMITERS`).
    """
    sample = [ln for ln in lines[:40] if ln.strip()][:20]
    best, best_n = None, 1
    for d in DELIMITERS:
        if d == decimal:
            continue
        counts = {len(split_cells(ln, d)) for ln in sample}
        if len(counts) == 1 and (n := counts.pop()) > best_n:
            best, best_n = d, n
    return best
