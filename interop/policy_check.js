// node-opcua over Basic256Sha256 with the certificate and key it is given (the test makes one whose key
// is too short for the policy, decision 101): does it get a session, and what is it told?
// argv: endpoint certPem keyPem applicationUri pkiDir
// Prints {session, status}: whether CreateSession/ActivateSession succeeded, and the status code's name
// node-opcua reports when it did not.
"use strict";
const { OPCUAClient, AttributeIds } = require("node-opcua-client");
const { done, main, secureOptions } = require("./lib");

main(async () => {
  const [endpoint, certificateFile, privateKeyFile, applicationUri, pkiDir] = process.argv.slice(2);
  const client = OPCUAClient.create(await secureOptions(certificateFile, privateKeyFile, applicationUri, pkiDir));
  let session = false;
  let status = "";
  try {
    await client.connect(endpoint);
    const s = await client.createSession();
    await s.read({ nodeId: "i=2259", attributeId: AttributeIds.Value });
    session = true;
    await s.close();
  } catch (err) {
    const match = /Bad\w+/.exec(String(err && err.message));
    status = match ? match[0] : String(err && err.message);
  } finally {
    await client.disconnect().catch(() => {});
  }
  await done({ session, status });
});
