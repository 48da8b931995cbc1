"""The one error that means "your input is wrong".

Every error the package raises about something a user gave it (a config file, a recording, a scenario, a
register address or value, a snapshot, a command-line flag, a certificate) derives from :class:`UserError`.
The command line catches exactly this class: it prints the message on one line and exits with status 2.
Anything else that escapes is a bug and shows its traceback.

:class:`UserError` subclasses :class:`ValueError`, so code written against the older errors (which were
``ValueError`` subclasses) keeps catching them.
"""

from __future__ import annotations

__all__ = ["UserError"]


class UserError(ValueError):
    """Something the user gave is wrong; the message names the file, key, line, field, flag or register."""
