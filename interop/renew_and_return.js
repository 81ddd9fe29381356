// node-opcua over Basic256Sha256 with a short security token lifetime (decision 104): it renews its token
// every 1.5 s (75 % of 2 s) while it reads, each renewal verified by the server; it holds a subscription,
// so its session outlives its connection (OPC 10000-4 6.7). Once `uacell cert remove` has taken its
// certificate out of the trust list, its channel is closed, and node-opcua's own reconnection (a new
// channel, then ActivateSession of the same session; or a new session) must not bring it back.
// argv: endpoint certPem keyPem applicationUri pkiDir readyFile
// Writes its channel id to readyFile once it has read for 5 s. Prints {channelId, reads, failed, renewed,
// lost, after}: the reads' counts, how many renewals node-opcua saw answered, whether it saw its
// connection lost, and what a read on the same session gave 8 s later ("Good" only if it came back).
"use strict";
const fs = require("fs");
const { OPCUAClient, AttributeIds, ClientSubscription } = require("node-opcua-client");
const { done, main, secureOptions } = require("./lib");

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));
const SERVER_STATE = { nodeId: "i=2259", attributeId: AttributeIds.Value };

main(async () => {
  const [endpoint, certificateFile, privateKeyFile, applicationUri, pkiDir, readyFile] = process.argv.slice(2);
  const options = await secureOptions(certificateFile, privateKeyFile, applicationUri, pkiDir);
  const client = OPCUAClient.create({
    ...options,
    defaultSecureTokenLifetime: 2000,
    connectionStrategy: { maxRetry: 5, initialDelay: 200, maxDelay: 1000 },
  });
  let renewed = 0;
  let lost = false;
  client.on("security_token_renewed", () => renewed++);
  client.on("connection_lost", () => { lost = true; });
  await client.connect(endpoint);
  const channelId = client._secureChannel.channelId;
  const session = await client.createSession();
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 100, requestedLifetimeCount: 600, requestedMaxKeepAliveCount: 10,
    maxNotificationsPerPublish: 10, publishingEnabled: true, priority: 1,
  });
  await new Promise((resolve) => subscription.on("started", resolve));
  let reads = 0;
  let failed = 0;
  for (const until = Date.now() + 5000; Date.now() < until; await sleep(250)) {
    try {
      const value = await session.read(SERVER_STATE);
      if (value.statusCode.name === "Good") reads++; else failed++;
    } catch (err) {
      failed++;
    }
  }
  fs.writeFileSync(readyFile, String(channelId));
  for (const until = Date.now() + 20000; !lost && Date.now() < until; ) await sleep(100);
  await sleep(8000); // node-opcua's reconnection: up to five attempts
  let after;
  try {
    const value = await session.read(SERVER_STATE);
    after = value.statusCode.name;
  } catch (err) {
    after = `error: ${err.message.split("\n")[0]}`;
  }
  await client.disconnect().catch(() => {});
  await done({ channelId, reads, failed, renewed, lost, after });
});
