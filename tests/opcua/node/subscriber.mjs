// A measuring OPC UA subscriber in a compiled client stack's stead (node-opcua), for bench/bench_opcua.py
// --client node and tests/opcua/test_opcua_node_subscriber.py: one session, one subscription monitoring the given
// variables of every loop with the bench's parameters, counting what the bench's asyncua client counts.
//   node subscriber.mjs    (reads its settings as one JSON line on stdin, then waits for a line "go")
// Settings: {url, loops: [path], variables: [name], counted: [name], publish_ms, sampling_ms, queue, requests,
// settle, seconds, trace}. Prints one JSON line {"ready": true} once subscribed; after "go", waits `settle`
// seconds (initial values and the first publishes), prints {"start": true} and counts for `seconds`: per counted
// item (a loop's variable in `counted`) the notifications received, the publish responses that carried data and
// those that came more than 1.5 publishing intervals after the one before (no Publish request was waiting at the
// server when the publish was due), the subscription's status changes, and this process's CPU seconds per second
// (process.cpuUsage: every thread of the process; and its main thread's, the event loop's); then prints
// {"counts": ...} and ends its session. With `trace`,
// each counted item's values as [publish time, SourceTimestamp, value], the times in seconds (the publish time on
// this process's monotonic clock, the window's too), for the bench's account of what was missed.
//
// The lightest path node-opcua offers: the items are created in groups of 500 (one CreateMonitoredItems request
// each, as the bench's asyncua client does), and every publish response is taken whole in the subscription's
// "raw_notification" event (its DataChangeNotification's items by client handle), with no listener per item.
import { readFileSync } from "node:fs";
import { createInterface } from "node:readline";
import { performance } from "node:perf_hooks";
import {
  AttributeIds, ClientSidePublishEngine, ClientSubscription, MessageSecurityMode, OPCUAClient, SecurityPolicy,
  TimestampsToReturn,
} from "node-opcua-client";

const lines = createInterface({ input: process.stdin })[Symbol.asyncIterator]();
const nextLine = async () => {
  const { value, done } = await lines.next();
  if (done) throw new Error("stdin closed before the settings / go");
  return value;
};
const print = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
const sleep = (s) => new Promise((resolve) => setTimeout(resolve, 1000 * s));
const now = () => performance.now() / 1000;
// CPU seconds of this process's main thread (the event loop's: decoding and our handler), from Linux's /proc;
// process.cpuUsage counts every thread (V8's compiler and collector helpers, libuv's pool)
const mainThreadCpu = () => {
  const fields = readFileSync(`/proc/self/task/${process.pid}/stat`, "utf8").split(") ")[1].split(" ");
  return (Number(fields[11]) + Number(fields[12])) / 100;   // utime + stime, clock ticks of 1/100 s
};

const cfg = JSON.parse(await nextLine());
// Publish requests kept at the server (node-opcua keeps this many in its pipeline; the bench's --publish-requests)
ClientSidePublishEngine.publishRequestCountInPipeline = cfg.requests;
const client = OPCUAClient.create({
  applicationName: "valve-emulator-bench-subscriber",
  endpointMustExist: false,
  connectionStrategy: { maxRetry: 0, initialDelay: 100 },
  securityMode: MessageSecurityMode.None,
  securityPolicy: SecurityPolicy.None,
  requestedSessionTimeout: 3600000,   // asyncua's client's
});
let session;
let exitCode = 0;
try {
  await client.connect(cfg.url);
  session = await client.createSession();
  const ns = (await session.readNamespaceArray()).indexOf("urn:valve-emulator");
  // asyncua's create_subscription(publish_ms): lifetime 10000, keep-alive count 0.75 * session timeout / interval,
  // at most 10000 notifications a publish, priority 0
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: cfg.publish_ms, requestedLifetimeCount: 10000,
    requestedMaxKeepAliveCount: Math.max(1, Math.floor((session.timeout / cfg.publish_ms) * 0.75)),
    maxNotificationsPerPublish: 10000, publishingEnabled: true, priority: 0,
  });
  await new Promise((resolve, reject) => {
    subscription.once("started", resolve);
    subscription.once("internal_error", reject);
  });
  const counted = new Set(cfg.counted);
  const items = [];   // [path.variable, counted]
  for (const path of cfg.loops) {
    for (const v of cfg.variables) items.push([`${path}.${v}`, counted.has(v)]);
  }
  // client handle -> index of the item in `count` (a counted item) or -1
  const slot = new Map();
  const count = [];
  const names = [];
  const trace = [];
  for (let k = 0; k < items.length; k += 500) {
    const part = items.slice(k, k + 500);
    const group = await subscription.monitorItems(
      part.map(([id]) => ({ nodeId: `ns=${ns};s=${id}`, attributeId: AttributeIds.Value })),
      { samplingInterval: cfg.sampling_ms, queueSize: cfg.queue, discardOldest: true },
      TimestampsToReturn.Both);
    group.monitoredItems.forEach((item, j) => {
      const [id, isCounted] = part[j];
      if (isCounted) {
        slot.set(item.monitoringParameters.clientHandle, count.length);
        count.push(0);
        names.push(id);
        trace.push([]);
      } else {
        slot.set(item.monitoringParameters.clientHandle, -1);
      }
    });
  }
  const responses = { last: null, n: 0, late: 0 };
  const lost = [];
  const lateAfter = 1.5e-3 * cfg.publish_ms;
  subscription.on("raw_notification", (message) => {
    const at = now();
    let data = false;
    for (const notification of message.notificationData || []) {
      if (!notification || notification.schema.name !== "DataChangeNotification") continue;
      for (const item of notification.monitoredItems || []) {
        const k = slot.get(item.clientHandle);
        if (k === undefined || k < 0) continue;
        count[k] += 1;
        data = true;
        if (cfg.trace) trace[k].push([at, item.value.sourceTimestamp.getTime() / 1000, item.value.value.value]);
      }
    }
    if (data) {   // asyncua's client counts a response when one of its values reaches the handler
      if (responses.last !== null && at - responses.last > lateAfter) responses.late += 1;
      responses.last = at;
      responses.n += 1;
    }
  });
  subscription.on("status_changed", (status) => lost.push(status.name));
  print({ ready: true });
  if ((await nextLine()).trim() !== "go") throw new Error("expected go");
  await sleep(cfg.settle);
  const start = count.slice();
  const before = { ...responses };
  const lostBefore = lost.length;
  const cpu0 = process.cpuUsage();
  const main0 = mainThreadCpu();
  const t0 = now();
  print({ start: true });
  await sleep(cfg.seconds);
  const t1 = now();
  const cpu = process.cpuUsage(cpu0);
  const cpuMain = (mainThreadCpu() - main0) / cfg.seconds;
  const got = count.map((n, k) => n - start[k]);
  const perItem = (cfg.seconds * 1000) / cfg.publish_ms;
  const out = {
    capped: got.reduce((s, n) => s + Math.min(n, perItem), 0),
    raw: got.reduce((s, n) => s + n, 0),
    items: got.length,
    fewest: Math.min(...got),
    responses: responses.n - before.n,
    late: responses.late - before.late,
    cpu: (cpu.user + cpu.system) / 1e6 / cfg.seconds,
    cpu_main: cpuMain,
    lost: lost.slice(lostBefore),
    window: [t0, t1],
  };
  if (cfg.trace) out.trace = Object.fromEntries(names.map((id, k) => [id, trace[k]]));
  print({ counts: out });
  await subscription.terminate();
} catch (err) {
  exitCode = 1;
  print({ failed: String(err && err.message ? err.message : err) });
} finally {
  if (session) await session.close().catch(() => {});
  await client.disconnect();
}
// stdout to a pipe is written asynchronously: exit only once every line is out (a trace of a 100 ms row is one
// line of megabytes, which an exit right after the write cut short)
await new Promise((resolve) => process.stdout.write("", resolve));
process.exit(exitCode);
