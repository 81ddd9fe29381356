// Two node-opcua sessions: the second names the first's subscription in each subscription service
// (OPC 10000-4 5.13/5.14: Bad_SubscriptionIdInvalid for a subscription the session does not have),
// and asks to take it over with TransferSubscriptions (5.14.7: only a session of the same user; two
// anonymous sessions over an unsigned channel may not). Then SetTriggering (5.13.5) on the first's
// subscription, by the first and by the second, and Server.ResendData. Prints each answer's status code.
"use strict";
const { AttributeIds, DataType, MonitoringMode, TimestampsToReturn } = require("node-opcua-client");
const { connect, resolve, done, main, FILLER } = require("./lib");

const names = (results) => results.map((r) => (r.statusCode || r).name);

main(async () => {
  const endpoint = process.argv[2];
  const first = await connect(endpoint);
  const second = await connect(endpoint);
  const created = await first.session.createSubscription({
    requestedPublishingInterval: 100, requestedLifetimeCount: 60, requestedMaxKeepAliveCount: 10,
    maxNotificationsPerPublish: 0, publishingEnabled: true, priority: 1,
  });
  const id = created.subscriptionId;
  const out = {};
  out.deleteByOther = names((await second.session.deleteSubscriptions({ subscriptionIds: [id] })).results);
  out.publishingModeByOther = names(await second.session.setPublishingMode(false, [id]));
  try {
    await second.session.modifySubscription({
      subscriptionId: id, requestedPublishingInterval: 1000, requestedLifetimeCount: 60,
      requestedMaxKeepAliveCount: 10, maxNotificationsPerPublish: 0, priority: 1,
    });
    out.modifyByOther = "Good";
  } catch (err) {
    out.modifyByOther = String(err.message).match(/Bad\w+/)?.[0] ?? String(err.message);
  }
  const filler = await resolve(first.session, first.ns, "i=85", FILLER);
  const speed = await resolve(first.session, first.ns, filler, "/PackML:Status/PackML:MachSpeed");
  const items = await first.session.createMonitoredItems({
    subscriptionId: id,
    timestampsToReturn: TimestampsToReturn.Both,
    itemsToCreate: [MonitoringMode.Reporting, MonitoringMode.Sampling].map((monitoringMode, i) => ({
      itemToMonitor: { nodeId: speed, attributeId: AttributeIds.Value },
      monitoringMode,
      requestedParameters: { clientHandle: 700 + i, samplingInterval: 0, queueSize: 5, discardOldest: true },
    })),
  });
  const [trigger, linked] = items.results.map((r) => r.monitoredItemId);
  const triggering = { subscriptionId: id, triggeringItemId: trigger, linksToAdd: [linked, 999999], linksToRemove: [] };
  const answer = await first.session.setTriggering(triggering);
  out.triggeringByOwner = names(answer.addResults);
  try {
    await second.session.setTriggering(triggering);
    out.triggeringByOther = "Good";
  } catch (err) {
    out.triggeringByOther = String(err.message).match(/Bad\w+/)?.[0] ?? String(err.message);
  }
  const transfer = async (session) =>
    names((await session.transferSubscriptions({ subscriptionIds: [id], sendInitialValues: false })).results);
  out.transferByOther = await transfer(second.session);
  out.transferByOwner = await transfer(first.session);
  const modified = await first.session.modifySubscription({
    subscriptionId: id, requestedPublishingInterval: 1000, requestedLifetimeCount: 60,
    requestedMaxKeepAliveCount: 10, maxNotificationsPerPublish: 0, priority: 1,
  });
  out.modifiedInterval = modified.revisedPublishingInterval;
  // Server.ResendData (OPC 10000-5 9.3) on the first's subscription, by each session
  const resend = async (session) => (await session.call({
    objectId: "i=2253", methodId: "i=12873", inputArguments: [{ dataType: DataType.UInt32, value: id }],
  })).statusCode.name;
  out.resendByOwner = await resend(first.session);
  out.resendByOther = await resend(second.session);
  out.deleteByOwner = names((await first.session.deleteSubscriptions({ subscriptionIds: [id] })).results);
  for (const { client, session } of [first, second]) {
    await session.close();
    await client.disconnect();
  }
  await done(out);
});
