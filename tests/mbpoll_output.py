"""Running a command-line client (mbpoll above all) from an async test, and reading mbpoll's output."""

from __future__ import annotations

import asyncio


async def run(*argv: str, timeout: float = 10.0) -> tuple[int, str]:
    """Run ``argv`` to its end without blocking the event loop (the server under test runs on it): its exit
    status and its output, stdout and stderr together."""
    proc = await asyncio.create_subprocess_exec(*argv, stdout=asyncio.subprocess.PIPE,
                                                stderr=asyncio.subprocess.STDOUT)
    out, _ = await asyncio.wait_for(proc.communicate(), timeout)
    return proc.returncode, out.decode()


def mbpoll_values(text: str) -> dict[int, str]:
    """The ``[address]: value`` lines of mbpoll's output, as address -> value text."""
    pairs = [line.split(":", 1) for line in text.splitlines() if line.startswith("[")]
    return {int(a.strip("[]")): v.strip() for a, v in pairs}
