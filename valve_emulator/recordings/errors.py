"""The errors and the warning of the recordings package.

Every message starts with where the defect is -- ``file: line L, column 'name' (k): what`` -- and the same facts
are kept as attributes, so a caller can point at the cell without parsing the message back.
"""

from __future__ import annotations

from valve_emulator.errors import UserError

__all__ = ["RecordingError", "ReaderError", "RecordingWarning"]


class RecordingError(UserError):
    """A recording file or object that cannot be used; the message names file, line and column.

    Attributes
    ----------
    source : the file (or the recording's ``source``) at fault, ``None`` when the message does not name one.
    line : 1-based line number as an editor counts (the header is line 1), ``None`` when no line applies.
    column : name of the column at fault, ``None`` when no column applies.
    """

    def __init__(self, message: str, *, source: str | None = None, line: int | None = None,
                 column: str | None = None) -> None:
        super().__init__(message)
        self.source, self.line, self.column = source, line, column


class ReaderError(RecordingError):
    """A file that cannot be read as a recording; the message names the file and what was expected.

    A :class:`RecordingError` (hence a ``ValueError``), so callers that already handle bad standard recordings
    handle these too.
    """


class RecordingWarning(UserWarning):
    """Something in a recording file was tolerated but dropped (a truncated last line)."""
