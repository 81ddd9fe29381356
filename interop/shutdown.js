// A stop seen from node-opcua (OPC 10000-5 12.10): subscribed to ServerStatus.State (i=2259),
// SecondsTillShutdown (i=2992) and ShutdownReason (i=2993), it prints "subscribed" once the first
// values arrived, then collects what arrives until the connection ends (or 60 s pass) and prints one
// JSON object: the states, the seconds and the reasons, in arrival order.
// argv: endpoint
"use strict";
const { OPCUAClient, AttributeIds, TimestampsToReturn, ClientMonitoredItemGroup } = require("node-opcua-client");
const { done, main } = require("./lib");

main(async () => {
  const [endpoint] = process.argv.slice(2);
  const client = OPCUAClient.create({
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 1000 },
    requestedSessionTimeout: 60000,
  });
  await client.connect(endpoint);
  const ended = new Promise((resolve) => {
    client.on("connection_lost", () => resolve("connection_lost"));
    client.on("close", () => resolve("close"));
    setTimeout(() => resolve("timeout"), 60000);
  });
  const session = await client.createSession();
  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 50, requestedLifetimeCount: 600, requestedMaxKeepAliveCount: 10,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  const out = { states: [], seconds: [], reasons: [] };
  const names = ["states", "seconds", "reasons"];
  const items = ["i=2259", "i=2992", "i=2993"].map((nodeId) => ({ nodeId, attributeId: AttributeIds.Value }));
  const group = ClientMonitoredItemGroup.create(
    subscription, items, { samplingInterval: 0, queueSize: 10, discardOldest: true }, TimestampsToReturn.Both,
  );
  let announced = false;
  group.on("changed", (item, dataValue, index) => {
    const value = dataValue.value.value;
    out[names[index]].push(value && value.text !== undefined ? value.text : value);
    if (!announced && out.states.length) {
      announced = true;
      process.stdout.write("subscribed\n");
    }
  });
  out.end = await ended;
  done(out);
});
