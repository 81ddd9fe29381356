// node-opcua connected over Basic256Sha256 with a certificate the server trusts, while an administrator
// takes it out of the trust list with `uacell cert remove` (decision 100): the open channel is closed
// (OPC 10000-12 7.8.2.5), and a new connection with the same certificate is refused.
// argv: endpoint certPem keyPem applicationUri pkiDir readyFile
// Prints {before, lost, reconnected}: the server state read first, whether node-opcua saw its connection
// lost within 20 s, and whether a new client with the certificate got a session.
"use strict";
const fs = require("fs");
const { OPCUAClient, AttributeIds } = require("node-opcua-client");
const { done, main, secureOptions } = require("./lib");

main(async () => {
  const [endpoint, certificateFile, privateKeyFile, applicationUri, pkiDir, readyFile] = process.argv.slice(2);
  const options = await secureOptions(certificateFile, privateKeyFile, applicationUri, pkiDir);
  const client = OPCUAClient.create(options);
  const lost = new Promise((resolve) => {
    client.on("connection_lost", () => resolve(true));
    client.on("close", () => resolve(true));
    setTimeout(() => resolve(false), 20000);
  });
  await client.connect(endpoint);
  const session = await client.createSession();
  const before = (await session.read({ nodeId: "i=2259", attributeId: AttributeIds.Value })).value.value;
  fs.writeFileSync(readyFile, "ready");
  const wasLost = await lost;
  await client.disconnect().catch(() => {});
  let reconnected = false;
  const again = OPCUAClient.create(options);
  try {
    await again.connect(endpoint);
    const s = await again.createSession();
    await s.read({ nodeId: "i=2259", attributeId: AttributeIds.Value });
    reconnected = true;
    await s.close();
  } catch (err) {
    reconnected = false;
  } finally {
    await again.disconnect().catch(() => {});
  }
  await done({ before, lost: wasLost, reconnected });
});
