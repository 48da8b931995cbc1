"""``valve-emulator serve --processes N``: N server processes started, supervised and stopped by this one.

Each child is ``valve-emulator serve CONFIG --processes N --process-index I`` (slice ``I`` of the loops on port
``PORT + I``). The parent relays their output, prints which port holds which units once all listen, forwards
SIGINT/SIGTERM/SIGHUP, and stops them all within a second (a process that does not stop in time is killed).
If one of them exits on its own, the parent stops the others and exits with status 1.
"""

from __future__ import annotations

import argparse
import queue
import re
import signal
import subprocess
import sys
import threading
import time

from valve_emulator.errors import UserError

__all__ = ["STOP_GRACE", "run_processes"]

_LISTENING = re.compile(r"listening on (\S+):(\d+),")
#: Seconds the parent gives its processes to stop before it kills them (the whole stop stays under 1 s).
STOP_GRACE = 0.8


def _child_argv(args: argparse.Namespace, index: int) -> list[str]:
    argv = [sys.executable, "-m", "valve_emulator", "serve", str(args.config), "--processes", str(args.processes),
            "--process-index", str(index), "--host", args.host, "--port", str(args.port),
            "--time-scale", repr(args.time_scale), "--log-level", args.log_level]
    if args.uvloop:
        argv.append("--uvloop")
    if args.read_only:
        argv.append("--read-only")
    if args.max_connections is not None:
        argv += ["--max-connections", str(args.max_connections)]
    return argv


def run_processes(args: argparse.Namespace) -> int:
    """Start ``args.processes`` slices as child processes, print the layout, supervise and stop them."""
    from valve_emulator.config.layout import partition
    from valve_emulator.device.runtime import load_server_or_default

    if args.config is None:
        raise UserError("--processes needs a CONFIG with at least that many unit ids")
    config = load_server_or_default(args.config)   # fail here, once, rather than in N children
    slices = partition(config, args.processes)
    total, tick = len(config.loops), config.device.tick
    del config
    events: queue.Queue = queue.Queue()
    procs = [subprocess.Popen(_child_argv(args, i), stdout=subprocess.PIPE, text=True, bufsize=1)
             for i in range(args.processes)]

    def relay(i: int, proc: subprocess.Popen) -> None:
        listening = False
        for line in proc.stdout:
            m = None if listening else _LISTENING.search(line)
            if m:
                listening = True
                events.put(("ready", i, (m.group(1), int(m.group(2)))))
            else:
                print(f"[process {i}] {line}", end="", flush=True)
        events.put(("exit", i, None))

    relays = [threading.Thread(target=relay, args=(i, proc), daemon=True, name=f"serve-relay-{i}")
              for i, proc in enumerate(procs)]
    for thread in relays:
        thread.start()
    forwarded = (signal.SIGINT, signal.SIGTERM) + ((signal.SIGHUP,) if hasattr(signal, "SIGHUP") else ())
    previous = {sig: signal.signal(sig, lambda sig, _frame: events.put(("signal", sig, None))) for sig in forwarded}
    hup = getattr(signal, "SIGHUP", None)
    ready: dict[int, tuple[str, int]] = {}
    status = 0
    try:
        while True:
            try:
                kind, i, info = events.get(timeout=0.5)   # a timeout keeps the signal handlers responsive
            except queue.Empty:
                continue
            if kind == "ready":
                ready[i] = info
                if len(ready) == len(procs):
                    print(f"valve-emulator: {len(procs)} processes serve {total:,} loops; tick {tick:g} s, "
                          f"time-scale {args.time_scale:g}; Ctrl-C stops", flush=True)
                    for p, part in enumerate(slices):
                        host, port = ready[p]
                        print(f"valve-emulator: process {p} (pid {procs[p].pid}) listening on {host}:{port}, "
                              f"{part.describe()}", flush=True)
            elif kind == "signal" and i == hup:   # reload: each process re-reads the file itself
                for proc in procs:
                    if proc.poll() is None:
                        proc.send_signal(i)
            elif kind == "signal":
                break
            else:  # a process ended although nobody asked it to
                code = procs[i].wait()
                print(f"valve-emulator: process {i} exited with status {code}; stopping the others",
                      file=sys.stderr, flush=True)
                status = 1
                break
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _stop_all(procs)
        for thread in relays:   # let the processes' last lines out before ours
            thread.join(timeout=0.1)
    print("valve-emulator: stopped", flush=True)
    return status


def _stop_all(procs: list[subprocess.Popen]) -> None:
    """SIGTERM every running child, wait up to :data:`STOP_GRACE` s in total, then kill the rest."""
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
    deadline = time.monotonic() + STOP_GRACE
    for proc in procs:
        try:
            proc.wait(timeout=max(deadline - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
