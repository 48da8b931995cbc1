// An OPC UA client written independently of the emulator (node-opcua), run by tests/opcua/test_opcua_node.py:
// browse a loop, read PV (its status) and the EngineeringUnits of PV, OP and time, write OP (the loop has no
// controller, so OP is the operator's), subscribe to PV and time (values, statuses, timestamps), optionally over
// Basic256Sha256 Sign&Encrypt with a user name. Prints one JSON line with what it saw.
//   node client.mjs URL LOOP_PATH [--secure USER PASSWORD]
import {
  AttributeIds, ClientMonitoredItem, ClientSubscription, DataType, MessageSecurityMode, OPCUAClient,
  SecurityPolicy, TimestampsToReturn, UserTokenType,
} from "node-opcua-client";

const [url, loopPath, flag, userName, password] = process.argv.slice(2);
const secure = flag === "--secure";
const client = OPCUAClient.create({
  applicationName: "valve-emulator-node-test",
  endpointMustExist: false,
  connectionStrategy: { maxRetry: 0, initialDelay: 100 },
  securityMode: secure ? MessageSecurityMode.SignAndEncrypt : MessageSecurityMode.None,
  securityPolicy: secure ? SecurityPolicy.Basic256Sha256 : SecurityPolicy.None,
});
const out = {};
try {
  await client.connect(url);
  const identity = secure ? { type: UserTokenType.UserName, userName, password } : { type: UserTokenType.Anonymous };
  const session = await client.createSession(identity);
  const namespaces = await session.readNamespaceArray();
  const ns = namespaces.indexOf("urn:valve-emulator");
  const loop = `ns=${ns};s=${loopPath}`;
  const browsed = await session.browse(loop);
  out.children = browsed.references.map((r) => r.browseName.name);
  const pv = await session.read({ nodeId: `${loop}.pv`, attributeId: AttributeIds.Value });
  out.pv = pv.value.value;
  out.pv_status = pv.statusCode.name;
  // the EngineeringUnits property of some analog items, found by browsing as a SCADA does
  out.units = {};
  for (const name of ["pv", "op", "time"]) {
    const ref = (await session.browse(`${loop}.${name}`)).references.find((r) => r.browseName.name === "EngineeringUnits");
    const eu = ref ? (await session.read({ nodeId: ref.nodeId, attributeId: AttributeIds.Value })).value.value : null;
    out.units[name] = eu && { namespaceUri: eu.namespaceUri, unitId: eu.unitId, displayName: eu.displayName.text };
  }
  const written = await session.write({
    nodeId: `${loop}.op`, attributeId: AttributeIds.Value, value: { value: { dataType: DataType.Double, value: 61.5 } },
  });
  out.write_op = written.name;
  const refused = await session.write({
    nodeId: `${loop}.pv`, attributeId: AttributeIds.Value, value: { value: { dataType: DataType.Double, value: 1.0 } },
  });
  out.write_pv = refused.name;
  const op = await session.read({ nodeId: `${loop}.op`, attributeId: AttributeIds.Value });
  out.op = op.value.value;
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 100, requestedLifetimeCount: 100, requestedMaxKeepAliveCount: 10,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  // PV (moving towards the written OP's steady state) and the simulated time (changing at every tick)
  for (const name of ["pv", "time"]) {
    const item = ClientMonitoredItem.create(subscription, { nodeId: `${loop}.${name}`, attributeId: AttributeIds.Value },
      { samplingInterval: 100, discardOldest: true, queueSize: 10 }, TimestampsToReturn.Both);
    out[`${name}_notifications`] = [];
    out[`${name}_statuses`] = [];
    out[`${name}_stamps`] = [];   // [SourceTimestamp, ServerTimestamp, received], ms since the epoch
    item.on("changed", (dv) => {
      out[`${name}_notifications`].push(dv.value.value);
      out[`${name}_statuses`].push(dv.statusCode.name);
      out[`${name}_stamps`].push([dv.sourceTimestamp.getTime(), dv.serverTimestamp.getTime(), Date.now()]);
    });
  }
  await new Promise((resolve) => setTimeout(resolve, 2000));
  await subscription.terminate();
  await session.close();
  out.ok = true;
} catch (err) {
  out.ok = false;
  out.error = String(err && err.message ? err.message : err);
} finally {
  await client.disconnect();
}
console.log(JSON.stringify(out));
process.exit(out.ok ? 0 : 1);
