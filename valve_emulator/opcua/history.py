"""HistoryRead of every loop's PV, OP, SP and MV over the last few minutes (``serve --opcua-history 10m``).

The server hands each historized variable's data changes -- the values its publisher sends after every tick,
with the tick's SourceTimestamp -- to asyncua's history manager, which keeps them in SQLite
(:class:`asyncua.server.history_sql.HistorySQLite`, in memory unless a file is named) and drops what is
older than the period at each insert. A client reads them with HistoryRead (ReadRawModifiedDetails), e.g.
asyncua's ``Node.read_raw_history(start, end)``.

Each historized value costs an SQLite insert and delete per change, so history is meant for the loops a
historian or a test looks at, not for a fleet of thousands.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Collection, Iterable
from dataclasses import replace
from datetime import timedelta
from typing import Any

from valve_emulator.errors import UserError

__all__ = ["HISTORIZED", "HistoryError", "history_seconds", "historize", "refuse_unhistorized"]

#: The variables of every loop that are historized.
HISTORIZED = ("pv", "op", "sp", "mv")
_SECONDS = {"": 1.0, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}


class HistoryError(UserError):
    """A history period that is not a positive duration."""


def history_seconds(text: str, *, flag: str = "--opcua-history") -> float:
    """``text`` as seconds: a positive number with an optional unit, ``600``, ``600s``, ``10m``, ``10min``,
    ``2h``."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*(s|m|min|h)?\s*", text)
    seconds = float(match[1]) * _SECONDS[match[2] or ""] if match else 0.0
    if not seconds > 0:
        raise HistoryError(f"{flag} {text!r}: give a duration > 0 such as 600, 600s, 10m or 2h")
    return seconds


def _storage(path: str) -> Any:
    """asyncua's SQLite history with a table name it accepts for string node ids.

    asyncua names a node's table ``<ns>_<repr(identifier)>`` and then refuses its own name when the identifier
    is a string (the quotes of the repr fail its SQL-injection check), so string node ids such as
    ``Unit1.FIC101.pv`` could not be historized; here the table is named after a digest of the node id."""
    from asyncua.server.history_sql import HistorySQLite

    class StringIdHistory(HistorySQLite):
        def _get_table_name(self, node_id: Any) -> str:
            digest = hashlib.sha1(node_id.to_string().encode(), usedforsecurity=False).hexdigest()
            return f"{node_id.NamespaceIndex}_{digest}"

    return StringIdHistory(path)


async def historize(server: Any, node_ids: Iterable[Any], seconds: float, path: str = ":memory:") -> None:
    """Keep the data changes of ``node_ids`` for ``seconds`` in SQLite at ``path`` and answer HistoryRead of
    them; their ``Historizing`` attribute and ``HistoryRead`` access bit are the caller's to set."""
    manager = server.iserver.history_manager
    storage = _storage(path)
    manager.set_storage(storage)
    await storage.init()
    period = timedelta(seconds=seconds)
    for node_id in node_ids:
        await manager.historize_data_change(server.get_node(node_id), period=period)


def refuse_unhistorized(server: Any, historized: Collection[Any]) -> None:
    """Answer HistoryRead of a node outside ``historized`` with ``BadHistoryOperationUnsupported`` (asyncua
    would answer an empty Good history and log an error for each such read)."""
    from asyncua import ua

    manager = server.iserver.history_manager
    read = manager.read_history

    async def read_history(params: ua.HistoryReadParameters) -> list[ua.HistoryReadResult]:
        kept = [rv for rv in params.NodesToRead if rv.NodeId in historized]
        answers = iter(await read(replace(params, NodesToRead=kept)) if kept else [])
        unsupported = ua.StatusCode(ua.StatusCodes.BadHistoryOperationUnsupported)
        return [next(answers) if rv.NodeId in historized else ua.HistoryReadResult(StatusCode=unsupported)
                for rv in params.NodesToRead]

    manager.read_history = read_history
