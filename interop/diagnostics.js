// Read ServerDiagnostics (EnabledFlag, ServerDiagnosticsSummary, SessionDiagnosticsArray) and call
// Server.GetMonitoredItems for a subscription of this session, as a node-opcua client.
"use strict";
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, ClientSubscription, ClientMonitoredItem,
  TimestampsToReturn, DataType, UserTokenType,
} = require("node-opcua-client");
const { done, main } = require("./lib");

async function until(probe, predicate, timeoutMs = 20000) {
  const deadline = Date.now() + timeoutMs;
  for (;;) {
    const value = await probe();
    if (predicate(value)) return value;
    if (Date.now() > deadline) throw new Error(`condition not met: ${JSON.stringify(value)}`);
    await new Promise((r) => setTimeout(r, 100));
  }
}

main(async () => {
  const endpoint = process.argv[2];
  const client = OPCUAClient.create({
    endpointMustExist: false, clientName: "uacell diagnostics probe",
    securityMode: MessageSecurityMode.None, securityPolicy: SecurityPolicy.None,
    connectionStrategy: { maxRetry: 2, initialDelay: 200, maxDelay: 1000 },
  });
  await client.connect(endpoint);
  const session = await client.createSession();
  const read = async (nodeId) => (await session.read({ nodeId, attributeId: AttributeIds.Value })).value.value;
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 250, requestedLifetimeCount: 100, requestedMaxKeepAliveCount: 10, publishingEnabled: true,
  });
  await new Promise((resolve) => subscription.on("started", resolve));
  const item = ClientMonitoredItem.create(subscription, { nodeId: "i=2258", attributeId: AttributeIds.Value },
    { samplingInterval: 250, queueSize: 1, discardOldest: true }, TimestampsToReturn.Both);
  await new Promise((resolve, reject) => { item.on("initialized", resolve); item.on("err", reject); });

  const out = { enabledFlag: await read("i=2294") };
  const summary = await until(() => read("i=2275"), (s) => s && s.currentSubscriptionCount >= 1);
  out.summary = { currentSessionCount: summary.currentSessionCount, currentSubscriptionCount: summary.currentSubscriptionCount,
    cumulatedSessionCount: summary.cumulatedSessionCount };
  const sessions = await until(() => read("i=3707"),
    (arr) => arr && arr.some((s) => s.sessionName.startsWith("uacell diagnostics probe") && s.currentMonitoredItemsCount === 1));
  out.sessions = sessions.map((s) => ({
    sessionName: s.sessionName.startsWith("uacell diagnostics probe") ? "uacell diagnostics probe" : s.sessionName,
    currentSubscriptionsCount: s.currentSubscriptionsCount, currentMonitoredItemsCount: s.currentMonitoredItemsCount,
  }));
  const call = async (id) => session.call({
    objectId: "i=2253", methodId: "i=11492", inputArguments: [{ dataType: DataType.UInt32, value: id }],
  });
  const res = await call(subscription.subscriptionId);
  out.monitoredItems = {
    statusCode: res.statusCode.name,
    serverHandles: Array.from(res.outputArguments[0].value || []),
    clientHandles: Array.from(res.outputArguments[1].value || []),
  };
  out.monitoredItemId = item.monitoredItemId;
  out.clientHandle = item.monitoringParameters.clientHandle;
  out.unknownSubscription = (await call(987654)).statusCode.name;
  const [, , , userName, password] = process.argv;
  const security = await session.read({ nodeId: "i=3708", attributeId: AttributeIds.Value });
  out.securityAnonymous = security.statusCode.name;
  if (userName) {
    // an admin reads SessionSecurityDiagnosticsArray: node-opcua decodes the standard encoding
    const admin = await client.createSession({ type: UserTokenType.UserName, userName, password });
    // refreshed at most a second after a session change: wait until this admin session is in it
    const entries = await until(
      async () => (await admin.read({ nodeId: "i=3708", attributeId: AttributeIds.Value })).value.value || [],
      (arr) => arr.some((e) => e.clientUserIdOfSession === userName),
    );
    out.securityAdmin = entries.map((e) => ({
      clientUserIdOfSession: e.clientUserIdOfSession, authenticationMechanism: e.authenticationMechanism,
      encoding: e.encoding, transportProtocol: e.transportProtocol, securityPolicyUri: e.securityPolicyUri,
    }));
    await admin.close();
  }
  await subscription.terminate();
  await session.close();
  await client.disconnect();
  done(out);
});
