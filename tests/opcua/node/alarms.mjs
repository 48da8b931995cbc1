// An Alarms & Conditions client written independently of the emulator (node-opcua), run by
// tests/opcua/test_opcua_node.py: subscribe to the Server object's events, ask for a ConditionRefresh, wait for the
// loop's active PV alarm, acknowledge it with the standard Acknowledge method and wait for the acknowledged event.
// Prints one JSON line with what it saw.
//   node alarms.mjs URL LOOP_NAME
import {
  AttributeIds, ClientMonitoredItem, ClientSubscription, DataType, OPCUAClient, TimestampsToReturn,
  constructEventFilter,
} from "node-opcua-client";

const [url, loopName] = process.argv.slice(2);
const FIELDS = ["EventId", "SourceName", "Message", "Severity", "ConditionName", "Retain", "ActiveState.Id",
  "AckedState.Id", "ConditionId"];
const SERVER = "ns=0;i=2253";
const CONDITION_TYPE = "ns=0;i=2782";
const CONDITION_REFRESH = "ns=0;i=3875";
const ACKNOWLEDGE = "ns=0;i=9111";

const client = OPCUAClient.create({ applicationName: "valve-emulator-node-alarms", endpointMustExist: false,
  connectionStrategy: { maxRetry: 0, initialDelay: 100 } });
const out = {};
const events = [];
let wake = () => {};

function next(match, ms = 10000) {
  // the first event (already received or still to come) that matches
  return new Promise((resolve, reject) => {
    const timer = setTimeout(() => reject(new Error(`no matching event in ${ms} ms: ${JSON.stringify(events)}`)), ms);
    const look = () => {
      const found = events.find(match);
      if (found) { clearTimeout(timer); wake = () => {}; resolve(found); }
    };
    wake = look;
    look();
  });
}

function summary(e) {
  return { message: e.Message, severity: e.Severity, condition: e.ConditionName, retain: e.Retain,
    active: e["ActiveState.Id"], acked: e["AckedState.Id"], conditionId: e.ConditionId.toString() };
}

try {
  await client.connect(url);
  const session = await client.createSession();
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 100, requestedMaxKeepAliveCount: 10,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  const item = ClientMonitoredItem.create(subscription, { nodeId: SERVER, attributeId: AttributeIds.EventNotifier },
    { queueSize: 100, discardOldest: true, filter: constructEventFilter(FIELDS) }, TimestampsToReturn.Neither);
  item.on("changed", (values) => {
    const e = Object.fromEntries(FIELDS.map((f, i) => [f, values[i].value]));
    e.Message = e.Message && e.Message.text;
    events.push(e);
    wake();
  });
  await new Promise((resolve) => item.once("initialized", resolve));
  const refresh = await session.call({ objectId: CONDITION_TYPE, methodId: CONDITION_REFRESH,
    inputArguments: [{ dataType: DataType.UInt32, value: subscription.subscriptionId }] });
  out.refresh = refresh.statusCode.name;
  const raised = await next((e) => e.SourceName === loopName && e["ActiveState.Id"] === true);
  out.raised = summary(raised);
  const ack = await session.call({ objectId: raised.ConditionId, methodId: ACKNOWLEDGE, inputArguments: [
    { dataType: DataType.ByteString, value: raised.EventId },
    { dataType: DataType.LocalizedText, value: { text: "seen by node-opcua" } }] });
  out.acknowledge = ack.statusCode.name;
  out.acked = summary(await next((e) => e.SourceName === loopName && e["AckedState.Id"] === true));
  await subscription.terminate();
  await session.close();
  out.ok = true;
} catch (err) {
  out.ok = false;
  out.error = String(err && err.stack || err);
} finally {
  await client.disconnect();
}
console.log(JSON.stringify(out));
