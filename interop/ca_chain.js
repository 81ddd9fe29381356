// Client certificates issued by a plant's CA, from node-opcua: Basic256Sha256 SignAndEncrypt sessions whose
// certificate file holds the client's certificate followed by its issuing CA's (node-opcua sends that chain
// in OpenSecureChannel and its certificate alone in CreateSession).
// argv: endpoint pkiDir then, per client, label certPem keyPem applicationUri
// Prints one JSON object: per label, the ServerState the session read, or the error.
"use strict";
const { MessageSecurityMode, SecurityPolicy, AttributeIds } = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { done, main, newClient } = require("./lib");

async function session(endpoint, manager, certificateFile, privateKeyFile, applicationUri) {
  const client = newClient({
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile, privateKeyFile, applicationUri, applicationName: "uacell interop CA",
    clientCertificateManager: manager,
  });
  await client.connect(endpoint);
  try {
    const s = await client.createSession();
    const state = (await s.read({ nodeId: "i=2259", attributeId: AttributeIds.Value })).value.value;
    await s.close();
    return { state };
  } finally {
    await client.disconnect();
  }
}

main(async () => {
  const [endpoint, pkiDir, ...rest] = process.argv.slice(2);
  const manager = new OPCUACertificateManager({ rootFolder: pkiDir, automaticallyAcceptUnknownCertificate: true });
  await manager.initialize();
  const out = {};
  for (let i = 0; i + 3 < rest.length; i += 4) {
    const [label, cert, key, uri] = rest.slice(i, i + 4);
    try {
      out[label] = await session(endpoint, manager, cert, key, uri);
    } catch (err) {
      out[label] = { error: String(err.message || err) };
    }
  }
  done(out);
});
