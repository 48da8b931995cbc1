"""Stopping a background task of the device (the tick, the recorder) without swallowing a caller's cancel."""

from __future__ import annotations

import asyncio

__all__ = ["cancel_and_wait"]


async def cancel_and_wait(task: asyncio.Task | None) -> None:
    """Cancel ``task`` (None: nothing to do) and wait until it has finished its clean-up.

    The task's own :class:`asyncio.CancelledError` is absorbed; if the caller is itself being cancelled
    meanwhile, that cancellation is re-raised rather than swallowed.
    """
    if task is None:
        return
    task.cancel()
    try:
        await task
    except asyncio.CancelledError:
        current = asyncio.current_task()
        if current is not None and current.cancelling():
            raise
