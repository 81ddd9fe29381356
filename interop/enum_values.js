// Enumeration values out of range from node-opcua (OPC 10000-4): a BrowseDescription whose
// BrowseDirection is 5 beside a right one, a Read whose TimestampsToReturn is 9, a monitored item whose
// MonitoringMode is 7 beside a right one; then a plain Read, to show the session goes on. node-opcua
// refuses such numbers in its constructors, so each is set on the made request, which it encodes as is.
// argv: endpoint. Prints one JSON object.
"use strict";
const {
  BrowseRequest, ReadRequest, AttributeIds, TimestampsToReturn, MonitoringMode,
  CreateMonitoredItemsRequest, MonitoredItemCreateRequest,
} = require("node-opcua-client");
const { connect, done, main } = require("./lib");

async function fault(session, request) {
  try {
    const response = await session.performMessageTransaction(request);
    return { status: response.responseHeader.serviceResult.name, results: (response.results || []).map((r) => (r.statusCode ? r.statusCode.name : null)) };
  } catch (err) {
    return { error: String(err.message || err) };
  }
}

main(async () => {
  const [endpoint] = process.argv.slice(2);
  const { client, session } = await connect(endpoint);
  const out = {};

  const description = { nodeId: "i=85", resultMask: 63 };
  const browse = new BrowseRequest({ nodesToBrowse: [description, description], requestedMaxReferencesPerNode: 0 });
  browse.nodesToBrowse[0].browseDirection = 5;
  out.browse = await fault(session, browse);

  const read = new ReadRequest({ nodesToRead: [{ nodeId: "i=2258", attributeId: AttributeIds.Value }] });
  read.timestampsToReturn = 9;
  out.read = await fault(session, read);

  const subscription = await session.createSubscription2({
    requestedPublishingInterval: 200, requestedLifetimeCount: 300, requestedMaxKeepAliveCount: 10,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  const item = (handle) => new MonitoredItemCreateRequest({
    itemToMonitor: { nodeId: "i=2258", attributeId: AttributeIds.Value },
    monitoringMode: MonitoringMode.Reporting,
    requestedParameters: { clientHandle: handle, samplingInterval: 0, queueSize: 1, discardOldest: true },
  });
  const create = new CreateMonitoredItemsRequest({
    subscriptionId: subscription.subscriptionId, timestampsToReturn: TimestampsToReturn.Both, itemsToCreate: [item(1), item(2)],
  });
  create.itemsToCreate[0].monitoringMode = 7;
  out.create = await fault(session, create);
  await subscription.terminate();

  const after = await session.read({ nodeId: "i=2258", attributeId: AttributeIds.Value });
  out.after = after.statusCode.name;
  await session.close();
  await client.disconnect();
  await done(out);
});
