"""Running a client's coroutine from ``main``: Ctrl-C / SIGTERM set a stop event instead of killing it."""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from valve_emulator.errors import UserError

__all__ = ["client_main", "pause", "run_until_stopped"]

T = TypeVar("T")


async def _with_signals(body: Callable[[asyncio.Event], Awaitable[T]]) -> T:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    installed = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
            installed.append(sig)
        except (NotImplementedError, RuntimeError):  # not the main thread, or no signals here
            pass
    try:
        return await body(stop)
    finally:
        for sig in installed:
            loop.remove_signal_handler(sig)


def run_until_stopped(body: Callable[[asyncio.Event], Awaitable[T]]) -> T:
    """``asyncio.run(body(stop))`` where SIGINT and SIGTERM set ``stop`` (the body finishes cleanly)."""
    return asyncio.run(_with_signals(body))


async def pause(delay: float, stop: asyncio.Event | None) -> None:
    """Sleep ``delay`` s of wall time, returning early once ``stop`` is set."""
    if stop is None:
        await asyncio.sleep(max(delay, 0.0))
        return
    if stop.is_set():
        return
    try:
        await asyncio.wait_for(stop.wait(), timeout=max(delay, 0.0))
    except TimeoutError:
        pass


def client_main(prog: str, args: argparse.Namespace, options: Callable[[argparse.Namespace], Any],
                body: Callable[[Any, asyncio.Event], Awaitable[Any]]) -> int:
    """The shared ``main`` of the clients: settings from the flags, then run until done or stopped.

    Exit codes: 0 done (also after Ctrl-C / SIGTERM), 1 the device failed (connection, Modbus exception, a
    device that restarted under a recording: an ``OSError``), 2 bad settings (a :class:`UserError`). Errors are
    one line on stderr, prefixed with ``prog``; anything else is a bug and shows its traceback.
    """
    try:
        opts = options(args)
    except UserError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    try:
        run_until_stopped(lambda stop: body(opts, stop))
    except UserError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    return 0
