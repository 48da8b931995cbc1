"""Messages between the device process and its OPC UA process: calls with answers, and notes without.

One stream socket (a ``socketpair``) joins the two; each message is a 4-byte length and a pickle (both ends are
this package, started by the device process: nothing else can write to the socket). Either end may:

- :meth:`Channel.call` ``(op, *args)`` and await the other end's answer: its handler's return value, or the
  exception it raised, raised here again (``RegisterValueError`` stays ``RegisterValueError``);
- :meth:`Channel.note` ``(op, *args)``: no answer, never blocks (the device's tick sends one per tick: if the
  other end stops reading, notes are dropped once :data:`MAX_BUFFERED` bytes wait, rather than the tick).

Handlers run in the order messages arrive; a coroutine handler runs as its own task so a slow one holds up
no other message.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import pickle
import socket
import struct
from collections.abc import Callable
from typing import Any

__all__ = ["Channel", "ChannelClosed", "MAX_BUFFERED", "read_first"]

_log = logging.getLogger(__name__)
_LENGTH = struct.Struct("<I")
#: Bytes a peer may leave unread before notes to it are dropped.
MAX_BUFFERED = 1 << 20


class ChannelClosed(ConnectionError):
    """The other process closed the channel (it stopped or died)."""


class Channel:
    """One end of the socket: ``handlers`` maps an op to what answers it; :meth:`run` reads until the other end
    closes (then every pending call raises :class:`ChannelClosed`)."""

    def __init__(self, sock: socket.socket, handlers: dict[str, Callable[..., Any]]) -> None:
        self.sock, self.handlers = sock, handlers
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._calls: dict[int, asyncio.Future] = {}
        self._ids = itertools.count(1)
        self._tasks: set[asyncio.Task] = set()
        #: notes not sent because the other end had :data:`MAX_BUFFERED` bytes unread
        self.dropped = 0
        self.closed = asyncio.Event()

    async def open(self) -> None:
        self._reader, self._writer = await asyncio.open_connection(sock=self.sock, limit=1 << 26)

    def _send(self, message: tuple) -> None:
        if self._writer is None or self._writer.is_closing():
            raise ChannelClosed("the other OPC UA process is gone")
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self._writer.write(_LENGTH.pack(len(data)) + data)

    def note(self, op: str, *args: Any) -> None:
        """Send ``op(*args)`` without waiting for anything; dropped if the other end is not reading."""
        writer = self._writer
        if writer is None or writer.is_closing():
            return
        if writer.transport.get_write_buffer_size() > MAX_BUFFERED:
            self.dropped += 1
            return
        self._send(("note", 0, op, args))

    async def call(self, op: str, *args: Any) -> Any:
        """``op(*args)`` at the other end: its answer, or its exception raised here."""
        ident = next(self._ids)
        fut = asyncio.get_running_loop().create_future()
        self._calls[ident] = fut
        try:
            self._send(("call", ident, op, args))
            return await fut
        finally:
            self._calls.pop(ident, None)

    async def run(self) -> None:
        """Read and dispatch messages until the other end closes."""
        reader = self._reader
        try:
            while True:
                head = await reader.readexactly(_LENGTH.size)
                kind, ident, op, payload = pickle.loads(await reader.readexactly(_LENGTH.unpack(head)[0]))
                if kind == "answer":
                    self._answered(ident, op, payload)
                else:
                    self._dispatch(kind, ident, op, payload)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            self.closed.set()
            for fut in self._calls.values():
                if not fut.done():
                    fut.set_exception(ChannelClosed("the other OPC UA process is gone"))

    def _answered(self, ident: int, ok: bool, payload: Any) -> None:
        fut = self._calls.get(ident)
        if fut is None or fut.done():
            return
        if ok:
            fut.set_result(payload)
        else:
            fut.set_exception(payload)

    def _dispatch(self, kind: str, ident: int, op: str, args: tuple) -> None:
        try:
            result = self.handlers[op](*args)
        except Exception as exc:
            self._answer(kind, ident, False, exc)
            return
        if asyncio.iscoroutine(result):
            task = asyncio.get_running_loop().create_task(self._finish(kind, ident, result))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        else:
            self._answer(kind, ident, True, result)

    async def _finish(self, kind: str, ident: int, coro: Any) -> None:
        try:
            result = await coro
        except Exception as exc:
            self._answer(kind, ident, False, exc)
        else:
            self._answer(kind, ident, True, result)

    def _answer(self, kind: str, ident: int, ok: bool, payload: Any) -> None:
        if kind == "note":
            if not ok:
                _log.error("OPC UA process channel: a note failed", exc_info=payload)
            return
        with contextlib.suppress(ChannelClosed):
            try:
                self._send(("answer", ident, ok, payload))
            except (pickle.PicklingError, TypeError, AttributeError) as exc:   # an answer that does not pickle
                self._send(("answer", ident, False, RuntimeError(
                    f"an answer of type {type(payload).__name__} cannot be sent between processes: {exc}")))

    async def close(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()


def read_first(sock: socket.socket) -> Any:
    """The first message on ``sock``, a note, read before any event loop runs: its single argument."""
    def exactly(n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = sock.recv(n - len(data))
            if not chunk:
                raise ChannelClosed("the device process closed the channel before it said what to serve")
            data += chunk
        return data

    kind, _, _, args = pickle.loads(exactly(_LENGTH.unpack(exactly(_LENGTH.size))[0]))
    return args[0]
