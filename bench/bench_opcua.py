"""OPC UA beside Modbus under load, and under hostile input.

    python bench/bench_opcua.py [--mode process|in-process] [--loops 1000] [--clients 5] [--publish 1000]
        [--sampling MS] [--queue 1] [--vars pv,op,sp,mv] [--seconds 10] [--rounds 3] [--hostile 25000] [--profile]
        [--trace] [--client asyncua|node|asyncua,node]

**Load.** The device (``--loops`` loops of a fleet, tick 0.1 s, real time, PV measurement noise on every loop so
that PV and OP change at every tick) runs in this process; its OPC UA server runs in a process of its own (``--mode
process``, what ``valve-emulator serve --opcua`` runs) or in this process's event loop (``--mode in-process``).
Other processes open ``--clients`` OPC UA sessions (asyncua), each with one subscription (publishing interval
``--publish`` ms) monitoring ``--vars`` of every loop as a SCADA client does (sampling interval ``--sampling`` ms,
by default the publishing interval, and queue size ``--queue``, by default 1: the latest value), and one Modbus
client (a process of its own) polls 125 holding registers at 10 Hz, beside an OPC UA session that reads one value
every 0.1 s (the latency another session sees). Over a ``--seconds`` window: the tick's lateness against its
absolute deadline (p50, p99) beside the same fleet and poller without OPC UA measured in the same run (target:
within 1 ms of it, 10 ticks/s, no overrun), and the share of the pv/op values each client received: every pv/op item
should bring one new value per publishing interval (both change every tick), ``seconds / publishing interval`` per
item in the window; an item's count is capped at that, so that a client handed several values of one item per
interval (sampling 0, a longer queue) cannot make up for items it missed and "received" cannot exceed 100 % (target
>= 99 %). Beside it, uncapped, the pv/op notifications per item and publishing interval the median client got (1
when sampling honours the publishing interval; about publishing interval / tick with ``--sampling 0 --queue 0``),
and the share of publish responses that came more than 1.5 intervals after the one before: the client had no Publish
request at the server when the publish was due (asyncua's client keeps one at a time and sends the next once it has
taken in the last response), so the server publishes when the request comes, and with a queue of one the values
handed meanwhile replace the ones waiting. Also the CPU time of the device process, of the OPC UA process and of the
median client process per second, and the OPC UA process's CPU per notification handed to a subscription (the cost
of a notification, and so the cores a load needs) and of it the hand-off's (``OpcUaCounters.handing_cpu``: sampling
and handing to the items' queues; the process's figure also holds the encoding of what the clients took, so it moves
with their delivery, this one does not), the ticks the publisher deferred (out of its budget: in the
device's process) and those it skipped (behind the device: a newer tick came before it was done with the last).
Medians over ``--rounds``. ``--client``: the sessions' client stack, asyncua (Python, the default) or node
(node-opcua, ``tests/opcua/node/subscriber.mjs``, started by each session's process; ``npm ci`` in
``tests/opcua/node`` first): the same subscription, items and counts, reported over its stdout as JSON, its CPU per
second measured by itself; a client that keeps up where asyncua's, decoding every notification in Python, needs a
whole core at 20,000 notifications/s. Both, comma-separated, alternate their rounds in one run with the baseline's
and print a column each. ``--trace``: each client also reports what it missed -- which publishes lacked which
pv/op items, by loop decile, and whether the value after each miss was sampled two intervals after the one before
it (a sample lost at the server) or one (the item's samples moved a publish later) (:func:`missed`). ``--profile``
profiles the OPC UA server in process (cProfile) and prints where its time goes.

**Hostile.** ``--hostile N`` malformed OPC UA messages (``tests/opcua/hostile.py``: random bytes, absurd
and tiny sizes, garbage after Hello, truncated chunks, bad sequence numbers, junk OpenSecureChannel, TLS
ClientHello) from 4 threads of another process while the device ticks and a Modbus client and an OPC UA
client read once a second: crashes, ticks per second, overruns, normal reads answered (default 25,000: about
5 s; 0: skip).
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import contextlib
import multiprocessing as mp
import os
import statistics
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "tests" / "opcua"))

from bench_scale import fleet_mapping  # noqa: E402
from common import machine, table  # noqa: E402

COUNTED = ("pv", "op")
#: Seconds between the clients' probes of the server, and the probe's timeout (asyncua's default: 1 s).
WATCHDOG = 5.0


@dataclass(frozen=True)
class Subscribing:
    """What each OPC UA client subscribes to: ``variables`` of every loop, one subscription publishing every
    ``publish_ms``, each item sampled every ``sampling_ms`` with a queue of ``queue`` values; the client keeps
    ``requests`` Publish requests at the server; ``trace``: each client keeps every pv/op value's SourceTimestamp and
    the publish it came in, and reports what it missed (:func:`missed`); ``client``: the subscribing client's stack,
    ``asyncua`` (Python, in the client's process) or ``node`` (node-opcua, ``tests/opcua/node/subscriber.mjs``, a
    child of the client's process) run with ``node_args`` (V8's and Node's options: a profile, the heap)."""

    variables: tuple[str, ...]
    publish_ms: float
    sampling_ms: float
    queue: int
    requests: int = 1
    trace: bool = False
    client: str = "asyncua"
    node_args: tuple[str, ...] = ()


async def keep_publish_requests(client, subscription, extra: int) -> None:
    """Keep ``extra`` Publish requests at the server beside the one asyncua's client keeps, for ``subscription``
    (the client's only one), as OPC UA Part 4 §5.13.5 advises a client (several Publish requests queued at the
    server, so that a publish never waits for the client's next request; a SCADA client does). asyncua 2.1.0's
    client keeps one per session and sends the next once it has taken in the last response, with no setting for
    more; these loops add requests through its public calls (``UaClient.publish``, ``Subscription.publish_callback``),
    each acknowledging what it received with its next request. Runs until cancelled or the session closes."""
    from asyncua import ua

    async def one() -> None:
        acks: list = []
        while True:
            try:
                response = await client.uaclient.publish(acks)
            except ua.UaStatusCodeError as exc:
                if exc.code == ua.StatusCodes.BadTimeout:   # as asyncua's own loop: send the next one
                    acks = []
                    continue
                return
            except (TimeoutError, ConnectionError, ua.UaError):
                return   # the session is closing
            params, acks = response.Parameters, []
            if not params.SubscriptionId:
                return
            await subscription.publish_callback(params)
            if params.NotificationMessage.NotificationData:
                acks.append(ua.SubscriptionAcknowledgement(SubscriptionId=params.SubscriptionId,
                                                           SequenceNumber=params.NotificationMessage.SequenceNumber))

    await asyncio.gather(*(one() for _ in range(extra)))


@dataclass(frozen=True)
class ClientCounts:
    """What one client process counted over its window (:func:`_client`), sent to the bench as ``("counts",
    ClientCounts)``: ``capped``, the pv/op values received with each item's count capped at one per publishing
    interval; ``raw``, the same uncapped; ``polled``, Modbus polls answered (the poller); ``lost``, the statuses of the
    subscriptions that ended during the window; ``responses``, the publish responses with data, and ``late``, those
    more than 1.5 intervals after the one before; ``cpu``, the process's CPU seconds per second (node: every thread
    of the node process); ``reads``, the probe's read times, s (the poller); ``poll``, whether this is the poller
    rather than a session; ``missed``, with ``--trace``, what the session missed (:func:`missed`); ``cpu_main``,
    the node client's event-loop thread's CPU seconds per second (nan for asyncua)."""

    capped: float
    raw: int
    polled: int = 0
    lost: tuple[str, ...] = ()
    responses: int = 0
    late: int = 0
    cpu: float = float("nan")
    reads: tuple[float, ...] = ()
    poll: bool = False
    missed: dict | None = None
    cpu_main: float = float("nan")


NODE_DIR = ROOT / "tests" / "opcua" / "node"
#: Seconds each client lets the initial values and the first publishes settle before its window.
SETTLE = 3.0


def _node_client(url: str, loops: list[str], sub: Subscribing, seconds: float, go, out_q) -> None:
    """:func:`_client`'s session in node-opcua (``tests/opcua/node/subscriber.mjs``, the same subscription and
    counts; its own CPU from ``process.cpuUsage``), relayed to ``out_q`` in :func:`_client`'s messages."""
    import json
    import shutil
    import subprocess

    node = shutil.which("node")
    if node is None or not (NODE_DIR / "node_modules" / "node-opcua-client").is_dir():
        out_q.put(("failed", f"--client node needs node and `npm ci` in {NODE_DIR}"))
        return
    settings = {"url": url, "loops": loops, "variables": list(sub.variables), "counted": list(COUNTED),
                "publish_ms": sub.publish_ms, "sampling_ms": sub.sampling_ms, "queue": sub.queue,
                "requests": sub.requests, "settle": SETTLE, "seconds": seconds, "trace": sub.trace}
    proc = subprocess.Popen([node, *sub.node_args, str(NODE_DIR / "subscriber.mjs")], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, cwd=NODE_DIR)
    proc.stdin.write(json.dumps(settings) + "\n")
    proc.stdin.flush()

    def message() -> dict:
        for line in proc.stdout:
            if line.startswith("{"):
                got = json.loads(line)
                if "failed" in got:
                    raise RuntimeError(got["failed"])
                return got
        raise RuntimeError(f"the node subscriber ended (exit code {proc.wait()})")

    try:
        message()   # ready
        out_q.put(("ready",))
        go.wait()
        proc.stdin.write("go\n")
        proc.stdin.flush()
        message()   # start
        out_q.put(("start",))
        r = message()["counts"]
    except RuntimeError as exc:
        out_q.put(("failed", str(exc)))
        proc.kill()
        return
    finally:
        proc.stdin.close()
    proc.wait(60)
    trace = {item: [(at, stamp) for at, stamp, _ in values] for item, values in r["trace"].items()} \
        if sub.trace else None
    out_q.put(("counts", ClientCounts(
        capped=r["capped"], raw=r["raw"], lost=tuple(r["lost"]), responses=r["responses"], late=r["late"],
        cpu=r["cpu"], missed=missed(trace, tuple(r["window"]), sub.publish_ms / 1000, loops) if sub.trace else None,
        cpu_main=r["cpu_main"])))


def _client(url: str, modbus_port: int, loops: list[str], sub: Subscribing, seconds: float, poll: bool, go,
            out_q) -> None:
    """One OPC UA session subscribed to ``sub.variables`` of every loop, or with ``poll`` the Modbus poller and (with
    ``url``) a probe of another session's reads (one pv read every 0.1 s, timed), in a process of its own (asyncua's
    client costs about as much per notification as its server: clients sharing a process would be what limits the
    count, and a poller beside a session would count the session's event loop, not the device's answers). Puts
    ``ready`` once subscribed, waits for ``go``, then counts for ``seconds`` after 3 s of settling the notifications
    of each pv and op item, the publish responses and those that came more than 1.5 publishing intervals after the
    one before (the client had no Publish request at the server when the publish was due: asyncua's client keeps
    one), and puts its :class:`ClientCounts`."""
    if sub.client == "node" and url and not poll:
        _node_client(url, loops, sub, seconds, go, out_q)
        return
    import logging

    import psutil
    from asyncua import Client
    from pymodbus.client import AsyncModbusTcpClient

    logging.basicConfig(level=logging.ERROR)
    for name in ("pymodbus", "asyncua"):
        logging.getLogger(name).setLevel(logging.ERROR)

    async def session(count, lost, ready, responses, trace):
        # asyncua's client probes the server every watchdog interval and, by default, drops its session when a
        # probe takes over 1 s -- which the client's own event loop, decoding a publish of thousands of values
        # on a loaded 2-core machine, causes itself: 5 s, as a SCADA client's keep-alive would be
        client = Client(url, timeout=120, watchdog_intervall=WATCHDOG)
        async with client:
            ns = await client.get_namespace_index("urn:valve-emulator")
            class Handler:
                def datachange_notification(self, node, val, data):
                    at = subscription.last_publish_at   # the response this notification came in
                    if node.nodeid in count:
                        count[node.nodeid] += 1
                        if sub.trace:
                            trace.setdefault(node.nodeid.Identifier, []).append(
                                (at, data.monitored_item.Value.SourceTimestamp.timestamp()))
                    if at != responses["last"]:
                        late = responses["last"] is not None and at - responses["last"] > 1.5e-3 * sub.publish_ms
                        responses["last"], responses["n"], responses["late"] = \
                            at, responses["n"] + 1, responses["late"] + late

                def status_change_notification(self, status):   # ended: BadShutdown from the watchdog
                    lost.append(str(status.Status))

            subscription = await client.create_subscription(sub.publish_ms, Handler())
            requests = asyncio.create_task(keep_publish_requests(client, subscription, sub.requests - 1))
            nodes = [client.get_node(f"ns={ns};s={path}.{var}") for path in loops for var in sub.variables]
            count.update((n.nodeid, 0) for n in nodes if n.nodeid.Identifier.rsplit(".", 1)[1] in COUNTED)
            for k in range(0, len(nodes), 500):
                await subscription.subscribe_data_change(nodes[k:k + 500], queuesize=sub.queue,
                                                         sampling_interval=sub.sampling_ms)
            ready.set()
            try:
                await asyncio.sleep(3600)
            finally:
                requests.cancel()

    async def modbus(polled):
        client = AsyncModbusTcpClient("127.0.0.1", port=modbus_port, timeout=2, retries=0)
        await client.connect()
        try:
            while True:
                rr = await client.read_holding_registers(0, count=125, device_id=1)
                polled[0] += not rr.isError()
                await asyncio.sleep(0.1)
        finally:
            client.close()

    async def probe(reads):
        async with Client(url, timeout=30) as client:
            ns = await client.get_namespace_index("urn:valve-emulator")
            node = client.get_node(f"ns={ns};s={loops[0]}.pv")
            while True:
                started = time.perf_counter()
                await node.read_data_value(raise_on_bad_status=False)
                reads.append(time.perf_counter() - started)
                await asyncio.sleep(0.1)

    async def main():
        count, polled, ready, tasks, lost, reads, trace = {}, [0], asyncio.Event(), [], [], [], {}
        responses = {"last": None, "n": 0, "late": 0}
        if url and not poll:
            task = asyncio.create_task(session(count, lost, ready, responses, trace))
            tasks.append(task)
            waiting = asyncio.create_task(ready.wait())
            await asyncio.wait({task, waiting}, timeout=600, return_when=asyncio.FIRST_COMPLETED)
            if not ready.is_set():   # the session failed (its error) or timed out
                waiting.cancel()
                out_q.put(("failed", repr(task.exception()) if task.done() else "timed out subscribing"))
                return
        out_q.put(("ready",))
        await asyncio.get_running_loop().run_in_executor(None, go.wait)
        if poll:
            tasks.append(asyncio.create_task(modbus(polled)))
            if url:
                tasks.append(asyncio.create_task(probe(reads)))
        await asyncio.sleep(SETTLE)                    # initial values and the first publishes settle
        start, polled_before, lost_before, reads_before = dict(count), polled[0], len(lost), len(reads)
        before, cpu_before = dict(responses), psutil.Process().cpu_times()
        out_q.put(("start",))
        window = time.monotonic()
        await asyncio.sleep(seconds)
        window = (window, time.monotonic())
        got = [count[item] - start[item] for item in start]
        per_item = seconds * 1000 / sub.publish_ms
        cpu = psutil.Process().cpu_times()
        out_q.put(("counts", ClientCounts(
            capped=sum(min(n, per_item) for n in got), raw=sum(got), polled=polled[0] - polled_before,
            lost=tuple(lost[lost_before:]), responses=responses["n"] - before["n"],
            late=responses["late"] - before["late"],
            cpu=(cpu.user + cpu.system - cpu_before.user - cpu_before.system) / seconds,
            reads=tuple(reads[reads_before:]), poll=poll,
            missed=missed(trace, window, sub.publish_ms / 1000, loops) if sub.trace else None)))
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(main())


def missed(trace: dict, window: tuple[float, float], interval: float, loops: list[str]) -> dict:
    """What one client missed in ``window`` (its clock), from every pv/op value's publish time and SourceTimestamp
    (``--trace``): per publish, the counted items it did not carry; per item, those publishes; and for each miss the
    SourceTimestamps around it: the value after the miss sampled two intervals after the one before it is a sample
    lost at the server (two handed in one publishing interval, the older replaced by a queue of one); one interval
    after it, none was lost but the item's samples moved a publish later. ``interval``: the publishing (= sampling)
    interval, s. A publish that carried no counted item at all is not seen (the row's count shows it). ``misses``:
    for each miss inside the window, (the SourceTimestamp before it, the one after it, whether the publish that
    lacked the item or the next one came more than 1.5 intervals after the one before it), for :func:`classify`."""
    start, end = window
    publishes = sorted({at for values in trace.values() for at, _ in values if start <= at <= end})
    missing_by_publish = {at: 0 for at in publishes}
    place = {path: k for k, path in enumerate(loops)}
    by_loop = [0] * 10
    gaps: dict[str, int] = {}
    misses: list[tuple[float, float, bool]] = []
    late_publish = {at: k > 0 and at - publishes[k - 1] > 1.5 * interval for k, at in enumerate(publishes)}
    following = dict(zip(publishes, publishes[1:], strict=False))
    items_missing = 0
    for node, values in trace.items():
        times = [at for at, _ in values]
        here = set(times)
        lacking = [at for at in publishes if at not in here]
        if not lacking:
            continue
        items_missing += 1
        loop = place.get(node.rsplit(".", 1)[0], 0)
        by_loop[min(9, 10 * loop // max(len(loops), 1))] += len(lacking)
        for at in lacking:
            missing_by_publish[at] += 1
            k = bisect.bisect_left(times, at)
            if 0 < k < len(values):
                key = f"{round((values[k][1] - values[k - 1][1]) / interval)} intervals"
                misses.append((values[k - 1][1], values[k][1],
                               late_publish[at] or late_publish.get(following.get(at, at), False)))
            else:
                key = "at the window's edge"
            gaps[key] = gaps.get(key, 0) + 1
    counts = sorted(missing_by_publish.values(), reverse=True)
    return {"publishes": len(publishes), "items": len(trace), "items_missing": items_missing,
            "missed": sum(counts), "worst_publishes": counts[:5],
            "publishes_missing_some": sum(1 for c in counts if c), "by_loop_decile": by_loop, "gaps": gaps,
            "misses": misses}


#: What became of a missed pv/op value (:func:`classify`).
CAUSES = ("its tick skipped by the publisher", "its tick handed late", "handed on time, its publish late",
          "handed on time, replaced before its publish", "none lost: moved a publish later")


def classify(misses: list[tuple[float, float, bool]], off_grid: list, interval: float, period: float) -> dict:
    """What became of each missed value of one client (:func:`missed`'s ``misses``), from the OPC UA server's ticks
    not handed on the grid (``OpcUaCounters.off_grid``): the value after a miss one interval after the one before
    it: none was lost, the item's samples moved a publish later; two or more: the sample due one interval after the
    one before was lost -- if a tick within half a tick ``period`` of that time was skipped by the publisher (the
    sample taken at a later tick, handed into the interval of the next one) or handed after its hand-off on the
    grid, that is the cause; else it was handed on time and replaced (queue of one) before a publish took it,
    with the publish that lacked it, or the next one, late (the client's Publish request came late) or not."""
    out = dict.fromkeys(CAUSES, 0)
    for before, after, late_publish in misses:
        if round((after - before) / interval) <= 1:
            out[CAUSES[4]] += 1
            continue
        lost = before + interval
        near = [t for t in off_grid if abs(t.stamp - lost) <= period / 2]
        if any(t.skipped for t in near):
            out[CAUSES[0]] += 1
        elif near:
            out[CAUSES[1]] += 1
        else:
            out[CAUSES[2 if late_publish else 3]] += 1
    return out


async def _each(q, k: int, what: str, timeout: float) -> list[tuple]:
    """The next ``k`` messages of the client processes, each ``what`` (a failure ends the run with its error)."""
    loop, out = asyncio.get_running_loop(), []
    for _ in range(k):
        msg = await loop.run_in_executor(None, q.get, True, timeout)
        if msg[0] != what:
            raise RuntimeError(f"an OPC UA client process: {msg}")
        out.append(msg)
    return out


def _cpu(pid: int) -> float:
    """CPU seconds (user + system) process ``pid`` has used."""
    import psutil

    times = psutil.Process(pid).cpu_times()
    return times.user + times.system


@contextlib.asynccontextmanager
async def _opcua(mode: str, device, loops):
    """The OPC UA server over ``device`` in ``mode`` and the id of the process it runs in; mode none: none."""
    from valve_emulator.opcua import LocalSource, OpcUaProcess, OpcUaServer

    if mode == "none":
        yield None, os.getpid()
    elif mode == "process":
        async with OpcUaProcess(device, loops=loops, port=0) as opc:
            yield opc, opc.process.pid
    else:
        async with OpcUaServer(LocalSource(device), loops=loops, port=0) as opc:
            yield opc, os.getpid()


async def _load_round(mode: str, n: int, clients: int, sub: Subscribing, seconds: float, profiler=None) -> dict:
    """One window of the load (see the module docstring); ``profiler`` (cProfile) runs during the window."""
    import numpy as np

    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.server import EmulatorServer

    cfg = server_from_mapping(fleet_mapping(n))
    async with EmulatorServer(cfg, port=0, time_scale=1.0) as srv:
        for i in range(n):
            srv.device.bank.set_noise(i, 0.05)
        t0 = time.monotonic()
        async with _opcua(mode, srv.device, cfg.loops) as (opc, pid):
            build = time.monotonic() - t0
            paths = [f"Unit{srv.device.units[i]}.{lp.name}" for i, lp in enumerate(cfg.loops)]
            q, go, procs = mp.Queue(), mp.Event(), []
            url = opc.url if opc else ""
            for poll in [True] + [False] * (clients if opc else 0):   # the poller, then one at a time: a session
                procs.append(mp.Process(target=_client, args=(url, srv.port, paths, sub, seconds, poll, go, q),
                                        daemon=True))
                procs[-1].start()
                await _each(q, 1, "ready", 1800)
            go.set()
            await _each(q, len(procs), "start", 600)
            srv.device.jitter = type(srv.device.jitter)(4096)
            counters0 = await opc.counters() if opc else None
            sent0, deferred0, skipped0 = (counters0.notifications, counters0.deferred, counters0.skipped) if opc \
                else (0, 0, 0)
            ticks0, overruns0, t0, wall0 = srv.device.ticks, srv.device.overruns, time.monotonic(), time.time()
            cpu0, opc_cpu0 = _cpu(os.getpid()), _cpu(pid)
            if profiler is not None:
                profiler.enable()
            results = [msg[1] for msg in await _each(q, len(procs), "counts", seconds + 300)]
            elapsed, wall1 = time.monotonic() - t0, time.time()
            if profiler is not None:
                profiler.disable()
            cpu, opc_cpu = _cpu(os.getpid()) - cpu0, _cpu(pid) - opc_cpu0
            counters = await opc.counters() if opc else None
            sent = counters.notifications - sent0 if opc else 0
            deferred = counters.deferred - deferred0 if opc else 0
            skipped = counters.skipped - skipped0 if opc else 0
            newer = counters.sampled_newer - counters0.sampled_newer if opc else 0
            again = counters.sampled_again - counters0.sampled_again if opc else 0
            handing = counters.handing_cpu - counters0.handing_cpu if opc else 0.0
            off_grid = [t for t in counters.off_grid if wall0 - 1 <= t.stamp <= wall1] if opc else []
            ticks, overruns = srv.device.ticks - ticks0, srv.device.overruns - overruns0
            lateness = srv.device.jitter.values()
            for proc in procs:
                proc.join(30)
                if proc.is_alive():
                    proc.kill()
            poller = next(r for r in results if r.poll)
            polled, reads = poller.polled, poller.reads
            results = [r for r in results if not r.poll]   # the sessions
            counts, raw = [r.capped for r in results], [r.raw for r in results]
    expected = len(COUNTED) * n * seconds * 1000 / sub.publish_ms
    served = clients and opc is not None
    return {"build": build, "p50": float(np.percentile(lateness, 50)) * 1e3,
            "p99": float(np.percentile(lateness, 99)) * 1e3, "ticks": ticks / elapsed, "overruns": overruns,
            "received": min(counts) / expected if served else 1.0,
            "received_median": statistics.median(counts) / expected if served else 1.0,
            "per_interval": statistics.median(raw) / expected if served else float("nan"),
            "device_cpu": cpu / elapsed, "opcua_cpu": opc_cpu / elapsed if mode == "process" else float("nan"),
            "per_notification": 1e6 * opc_cpu / sent if sent and mode == "process" else float("nan"),
            "handing": 1e6 * handing / sent if sent and mode == "process" else float("nan"),
            "sent": sent / elapsed, "polled": polled / seconds,
            "lost": sum(len(r.lost) for r in results), "statuses": sorted({x for r in results for x in r.lost}),
            "late": sum(r.late for r in results) / max(sum(r.responses for r in results), 1) if served
            else float("nan"),
            "client_cpu": statistics.median(r.cpu for r in results) if served else float("nan"),
            "client_main_cpu": statistics.median(r.cpu_main for r in results) if served else float("nan"),
            "read_p50": 1e3 * float(np.percentile(reads, 50)) if reads else float("nan"),
            "read_p99": 1e3 * float(np.percentile(reads, 99)) if reads else float("nan"),
            "deferred": deferred, "skipped": skipped, "off_grid": off_grid, "newer": newer, "again": again,
            "trace": [r.missed for r in sorted(results, key=lambda r: r.capped)]}


def _profile(n: int, clients: int, sub: Subscribing, seconds: float) -> None:
    """Where the OPC UA server's time goes: cProfile of the in-process server under the same load."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    r = asyncio.run(_load_round("in-process", n, clients, sub, seconds, profiler))
    stats = pstats.Stats(profiler)
    waiting = {k: v for k, v in stats.stats.items() if k[2] in ("<method 'poll' of 'select.epoll' objects>",
                                                                 "<method 'get' of '_queue.SimpleQueue' objects>")}
    busy = {k: v for k, v in stats.stats.items() if k not in waiting}
    total = sum(t[2] for t in busy.values())
    sent = r["sent"] * seconds
    print(f"\nProfile (in process, the {seconds:g} s window: {total:.1f} s busy, {sent:,.0f} notifications, "
          f"{1e6 * total / max(sent, 1):.0f} µs of the event loop per notification): top functions by own time")
    rows = sorted(busy.items(), key=lambda kv: kv[1][2], reverse=True)[:25]
    print(table([(f"{Path(f).name}:{line} {fn}", f"{tt:.2f} s", f"{100 * tt / total:.1f} %", f"{nc:,}")
                 for (f, line, fn), (_, nc, tt, _, _) in rows], ("function", "own time", "share", "calls")))


def _attack_process(url: str, count: int, out_q) -> None:
    from hostile import attack

    out_q.put(attack("127.0.0.1", int(url.rsplit(":", 1)[1].split("/")[0]), url, count))


async def _hostile(count: int) -> dict:
    from asyncua import Client
    from pymodbus.client import AsyncModbusTcpClient

    from valve_emulator.config import server_from_mapping
    from valve_emulator.device.server import EmulatorServer
    from valve_emulator.opcua import OpcUaProcess

    cfg = server_from_mapping(fleet_mapping(10))
    async with EmulatorServer(cfg, port=0, time_scale=1.0) as srv, \
            OpcUaProcess(srv.device, loops=cfg.loops, port=0) as opc:
        q = mp.Queue()
        ticks0, overruns0, t0 = srv.device.ticks, srv.device.overruns, time.monotonic()
        proc = mp.Process(target=_attack_process, args=(opc.url, count, q), daemon=True)
        proc.start()
        reads = failures = 0
        path = f"Unit{srv.device.units[0]}.{cfg.loops[0].name}"
        async with Client(opc.url) as client, AsyncModbusTcpClient("127.0.0.1", port=srv.port) as mb:
            ns = await client.get_namespace_index("urn:valve-emulator")
            pv = client.get_node(f"ns={ns};s={path}.pv")
            while proc.is_alive():
                try:
                    await pv.read_value()
                    rr = await mb.read_holding_registers(0, count=31, device_id=srv.device.units[0])
                    reads += 1
                    failures += rr.isError()
                except Exception:
                    failures += 1
                await asyncio.sleep(1.0)
        sent = q.get(timeout=60)
        elapsed = time.monotonic() - t0
        return {"sent": sum(sent[k] for k in sent if k not in ("closed_by_server", "seconds")),
                "closed": sent["closed_by_server"], "seconds": sent["seconds"],
                "ticks": (srv.device.ticks - ticks0) / elapsed, "overruns": srv.device.overruns - overruns0,
                "error": srv.device.error, "reads": reads, "failures": failures}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mode", choices=("process", "in-process"), default="process")
    p.add_argument("--loops", type=int, default=1000)
    p.add_argument("--clients", type=int, default=5)
    p.add_argument("--publish", type=float, default=1000.0, metavar="MS", help="publishing interval")
    p.add_argument("--sampling", type=float, default=None, metavar="MS",
                   help="each item's sampling interval (default: the publishing interval; 0: every tick)")
    p.add_argument("--queue", type=int, default=1, help="each item's queue size (0: the server's maximum)")
    p.add_argument("--publish-requests", type=int, default=3, metavar="N",
                   help="Publish requests each client keeps at the server (1: asyncua's client alone)")
    p.add_argument("--vars", default="pv,op,sp,mv", help="the variables of every loop each client monitors")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--hostile", type=int, default=25_000)
    p.add_argument("--profile", action="store_true")
    p.add_argument("--client", default="asyncua",
                   help="the subscribing clients' stack: asyncua, node (node-opcua, tests/opcua/node/subscriber.mjs; "
                        "needs `npm ci` there), or both comma-separated (their rounds alternate in one run)")
    p.add_argument("--node-args", default="", metavar="ARGS",
                   help="options for node before the node client's script, space-separated, given as "
                        "--node-args=ARGS (e.g. '--cpu-prof --cpu-prof-dir=DIR', '--single-threaded-gc')")
    p.add_argument("--trace", action="store_true",
                   help="each client reports which publishes lacked which pv/op items, and the SourceTimestamps "
                        "around each miss")
    args = p.parse_args(argv)
    args.client = args.client.split(",")
    if not args.client or any(c not in ("asyncua", "node") for c in args.client) \
            or len(set(args.client)) < len(args.client):
        p.error(f"--client must be asyncua, node or both comma-separated, got {','.join(args.client)}")
    if args.publish_requests < 1:
        p.error(f"--publish-requests must be at least 1, got {args.publish_requests}")
    sub = Subscribing(variables=tuple(args.vars.split(",")), publish_ms=args.publish,
                      sampling_ms=args.publish if args.sampling is None else args.sampling, queue=args.queue,
                      requests=args.publish_requests, trace=args.trace, client=args.client[0],
                      node_args=tuple(args.node_args.split()))
    print(machine(), f"load average {os.getloadavg()[0]:.1f}")
    if args.rounds:
        _load(args, sub)
    if args.profile:
        _profile(args.loops, args.clients, sub, args.seconds)
    if args.hostile:
        _print_hostile(asyncio.run(_hostile(args.hostile)))


def _load(args: argparse.Namespace, sub: Subscribing) -> None:
    """Rounds of the fleet without OPC UA and with it (once per ``--client``), alternating; their medians side by
    side."""
    runs: dict[str, list[dict]] = {"none": [], **{client: [] for client in args.client}}
    for _ in range(args.rounds):
        for label in runs:
            mode = "none" if label == "none" else args.mode
            runs[label].append(asyncio.run(_load_round(mode, args.loops, args.clients if mode != "none" else 0,
                                                       replace(sub, client=label), args.seconds)))
            print(f"load average {os.getloadavg()[0]:.1f} after a round ({mode}"
                  f"{'' if mode == 'none' else ', ' + label + ' client'})", flush=True)
    med = {label: {k: statistics.median(r[k] for r in rs) for k in rs[0]
                   if k not in ("statuses", "trace", "off_grid")}
           for label, rs in runs.items()}
    base, served = med["none"], [med[client] for client in args.client]

    def row(name: str, without: str, with_: str) -> tuple[str, ...]:
        return (name, without, *(with_.format(**m) for m in served))

    print(f"\nLoad: {args.loops} loops at 10 Hz, {args.clients} OPC UA clients ({args.mode}) each monitoring "
          f"{','.join(sub.variables)} of every loop (publishing {sub.publish_ms:g} ms, sampling "
          f"{sub.sampling_ms:g} ms, queue {sub.queue}, {sub.requests} Publish requests kept at the server), "
          f"one Modbus poller at 10 Hz; "
          f"{args.seconds:g} s windows, median of {args.rounds} (baseline: the same without OPC UA, same run)")
    print(table([row("address space build", "", "{build:.1f} s"),
                 row("tick lateness p50 / p99 (target p99 within 1 ms of the baseline)",
                     f"{base['p50']:.1f} / {base['p99']:.1f} ms", "{p50:.1f} / {p99:.1f} ms"),
                 row("ticks per second, overruns", f"{base['ticks']:.2f}, {base['overruns']:.0f}",
                     "{ticks:.2f}, {overruns:.0f}"),
                 row("pv/op notifications received, worst client (target >= 99 %)", "", "{received:.1%}"),
                 row("pv/op notifications received, median client", "", "{received_median:.1%}"),
                 row("pv/op notifications per item and publishing interval, median client (uncapped)", "",
                     "{per_interval:.2f}"),
                 row("notifications handed to subscriptions per second", "", "{sent:,.0f}"),
                 row("device process CPU (s per s)", f"{base['device_cpu']:.2f}", "{device_cpu:.2f}"),
                 row("OPC UA process CPU (s per s)", "", "{opcua_cpu:.2f}"),
                 row("OPC UA CPU per notification", "", "{per_notification:.1f} µs"),
                 row("of it the hand-off's (sampling, handing to the items' queues), per notification", "",
                     "{handing:.1f} µs"),
                 row("publish responses more than 1.5 intervals after the one before (the client's Publish "
                     "request came late)", "", "{late:.1%}"),
                 row("OPC UA client process CPU (s per s), median client", "", "{client_cpu:.2f}"),
                 row("the same, its event loop's thread (node client)", "", "{client_main_cpu:.3f}"),
                 row("Modbus polls answered per second", f"{base['polled']:.1f}", "{polled:.1f}"),
                 row("another session's read of one value, p50 / p99 (one a 0.1 s)", "",
                     "{read_p50:.1f} / {read_p99:.1f} ms")],
                ("figure", "without OPC UA", *(f"with OPC UA, {client} client" for client in args.client))))
    for label, rs in runs.items():
        print(f"rounds ({label}): p99 " + ", ".join(f"{r['p99']:.1f}" for r in rs) + " ms; received "
              + ", ".join(f"{100 * r['received']:.1f}" for r in rs) + " %; subscriptions ended (status change) "
              + "during the window " + ", ".join(f"{r['lost']} {'/'.join(r['statuses'])}" for r in rs)
              + "; ticks the publisher deferred (out of its budget) " + ", ".join(f"{r['deferred']}" for r in rs)
              + "; ticks it skipped (behind the device) " + ", ".join(f"{r['skipped']}" for r in rs)
              + "; hand-off chunks that sampled a tick newer than theirs / the tick the one before sampled "
              + ", ".join(f"{r['newer']}/{r['again']}" for r in rs)
              + ("" if label == "none" else "; client CPU s/s (median client) "
                 + ", ".join(f"{r['client_cpu']:.2f}" for r in rs) + ", its event loop's thread "
                 + ", ".join(f"{r['client_main_cpu']:.3f}" for r in rs)))
    if sub.trace:
        for client in args.client:
            for k, r in enumerate(runs[client]):
                print(f"trace ({client}), round {k + 1}: ticks skipped "
                      f"{sum(t.skipped for t in r['off_grid'])}, handed late "
                      f"{sum(not t.skipped for t in r['off_grid'])}; each (tick, s past its hand-off on the grid, "
                      "the OPC UA process's CPU share since the tick before): "
                      + ", ".join(f"{'skipped' if t.skipped else 'late'} {t.tick} {t.late:+.3f} s {t.busy:.2f}"
                                  for t in r["off_grid"]))
                for rank, t in enumerate(r["trace"]):
                    if t is not None:
                        causes = classify(t.pop("misses"), r["off_grid"], sub.publish_ms / 1000,
                                          fleet_mapping(1)["device"]["tick"])
                        print(f"trace ({client}), round {k + 1}, client {rank + 1} of {len(r['trace'])} "
                              f"(worst first): {t}; each miss: {causes}")


def _print_hostile(h: dict) -> None:
    print(f"\nHostile: {h['sent']:,} malformed OPC UA messages in {h['seconds']:.0f} s "
          f"({h['sent'] / h['seconds']:,.0f}/s) from 4 threads of another process")
    print(table([("connections the server closed itself", f"{h['closed']:,}"),
                 ("ticks per second during the attack", f"{h['ticks']:.2f} (target 10 ± 1)"),
                 ("overruns", str(h["overruns"])), ("tick task failed", str(h["error"] is not None)),
                 ("normal reads (OPC UA + Modbus, 1/s) / failures", f"{h['reads']} / {h['failures']}")],
                ("figure", "value")))


if __name__ == "__main__":
    main()
