// A node-opcua client's absolute deadband (OPC 10000-4 7.22.2) on Filler1's Status.MachSpeed: the
// speed is set to 100, then drifts 100.5, 101.2, 101.9 and drops to 99.0, one SetMachSpeed call each.
// Prints the values the client was sent, in order. The standard compares each value with the last one
// reported ("last cached value"), so the drift is reported once it has gone beyond the deadband.
// Then, with node-opcua's own requests: a deadband on a LocalizedText (the task control's CurrentState)
// and a percent deadband beyond 100 %, and a subscription asking for a publishing interval of 0.
"use strict";
const {
  AttributeIds, ClientSubscription, ClientMonitoredItem, DataChangeFilter, DataChangeTrigger, DataType,
  DeadbandType, MonitoringMode, TimestampsToReturn,
} = require("node-opcua-client");
const { connect, resolve, done, main, FILLER, TASK_CONTROL } = require("./lib");

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const filler = await resolve(session, ns, "i=85", FILLER);
  const speed = await resolve(session, ns, filler, "/PackML:Status/PackML:MachSpeed");
  const setSpeed = await resolve(session, ns, filler, "/PackML:SetMachSpeed");
  const set = async (value) => {
    const result = await session.call({
      objectId: filler, methodId: setSpeed, inputArguments: [{ dataType: DataType.Float, value }],
    });
    if (!result.statusCode.isGood()) throw new Error(`SetMachSpeed ${value}: ${result.statusCode.toString()}`);
  };
  await set(100.0);
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 20, requestedLifetimeCount: 1000, requestedMaxKeepAliveCount: 20,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  await new Promise((r) => subscription.once("started", r));
  const values = [];
  const filter = new DataChangeFilter({
    trigger: DataChangeTrigger.StatusValue, deadbandType: DeadbandType.Absolute, deadbandValue: 1.0,
  });
  const item = ClientMonitoredItem.create(
    subscription,
    { nodeId: speed, attributeId: AttributeIds.Value },
    { samplingInterval: 0, discardOldest: false, queueSize: 10, filter },
    TimestampsToReturn.Both,
  );
  item.on("changed", (dv) => values.push(Math.round(dv.value.value * 1000) / 1000));
  const until = async (what, pred) => {
    const deadline = Date.now() + 20000;
    while (!pred()) {
      if (Date.now() > deadline) throw new Error(`waited for ${what}: ${JSON.stringify(values)}`);
      await new Promise((r) => setTimeout(r, 20));
    }
  };
  await until("the initial value", () => values.length >= 1);
  for (const value of [100.5, 101.2, 101.9, 99.0]) await set(value);
  await until("the last value", () => values.includes(99));
  const state = await resolve(session, ns, "i=85", `${TASK_CONTROL}/CurrentState`);
  const refused = await session.createMonitoredItems({
    subscriptionId: subscription.subscriptionId,
    timestampsToReturn: TimestampsToReturn.Both,
    itemsToCreate: [
      [state, filter],
      [speed, new DataChangeFilter({ trigger: DataChangeTrigger.StatusValue, deadbandType: DeadbandType.Percent, deadbandValue: 150 })],
    ].map(([nodeId, itemFilter], i) => ({
      itemToMonitor: { nodeId, attributeId: AttributeIds.Value },
      monitoringMode: MonitoringMode.Reporting,
      requestedParameters: { clientHandle: 900 + i, samplingInterval: 0, queueSize: 1, discardOldest: true, filter: itemFilter },
    })),
  });
  const fastest = await session.createSubscription({
    requestedPublishingInterval: 0, requestedLifetimeCount: 60, requestedMaxKeepAliveCount: 10,
    maxNotificationsPerPublish: 0, publishingEnabled: true, priority: 1,
  });
  await session.deleteSubscriptions({ subscriptionIds: [fastest.subscriptionId] });
  await subscription.terminate();
  await session.close();
  await client.disconnect();
  await done({
    values,
    refused: refused.results.map((r) => r.statusCode.name),
    revisedInterval: fastest.revisedPublishingInterval,
  });
});
