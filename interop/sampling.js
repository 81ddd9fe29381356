// Sampling intervals from node-opcua (OPC 10000-4 5.13.1.2, 7.21): items on ServerStatus.CurrentTime
// (i=2258, written once a second) asking for 3000 ms, 0 ms and -1 (the publishing interval) under a
// 200 ms subscription; what the server revised each to, and the values each got over about 4.5 s.
// argv: endpoint. Prints one JSON object.
"use strict";
const { AttributeIds, TimestampsToReturn, MonitoringMode } = require("node-opcua-client");
const { connect, done, main } = require("./lib");

main(async () => {
  const [endpoint] = process.argv.slice(2);
  const { client, session } = await connect(endpoint);
  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 200, requestedLifetimeCount: 300, requestedMaxKeepAliveCount: 10,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  const asked = [3000, 0, -1];
  const values = asked.map(() => []);
  subscription.on("received_notifications", (message) => {
    for (const data of message.notificationData || []) {
      for (const item of data.monitoredItems || []) {
        values[item.clientHandle - 800].push(item.value.sourceTimestamp ? item.value.sourceTimestamp.getTime() : null);
      }
    }
  });
  const started = Date.now();
  const created = await session.createMonitoredItems({
    subscriptionId: subscription.subscriptionId,
    timestampsToReturn: TimestampsToReturn.Both,
    itemsToCreate: asked.map((samplingInterval, i) => ({
      itemToMonitor: { nodeId: "i=2258", attributeId: AttributeIds.Value },
      monitoringMode: MonitoringMode.Reporting,
      requestedParameters: { clientHandle: 800 + i, samplingInterval, queueSize: 10, discardOldest: true },
    })),
  });
  await new Promise((resolve) => setTimeout(resolve, 4500));
  const out = {
    revised: created.results.map((r) => r.revisedSamplingInterval),
    status: created.results.map((r) => r.statusCode.name),
    counts: values.map((v) => v.length),
    elapsed: (Date.now() - started) / 1000,
  };
  await subscription.terminate();
  await session.close();
  await client.disconnect();
  await done(out);
});
