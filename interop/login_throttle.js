// Logins from node-opcua against uacell's login throttle: wrong passwords, then the right one.
// argv: endpoint certPem keyPem applicationUri pkiDir user password wrongAttempts
// Prints one JSON object: for each attempt, what the server answered and how long it took.
"use strict";
const { OPCUAClient, MessageSecurityMode, SecurityPolicy, UserTokenType } = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { done, main } = require("./lib");

async function attempt(endpoint, options, userName, password) {
  const client = OPCUAClient.create({
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 1000 },
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    requestedSessionTimeout: 60000,
    ...options,
  });
  const started = Date.now();
  let answer;
  try {
    await client.connect(endpoint);
    const session = await client.createSession({ type: UserTokenType.UserName, userName, password });
    answer = "Good";
    await session.close();
  } catch (err) {
    // A refusal names its status code; a dropped connection does not.
    const match = /(Bad\w+)/.exec(String(err.message));
    answer = match ? match[1] : `error: ${err.message}`;
  }
  await client.disconnect().catch(() => {});
  return { answer, seconds: (Date.now() - started) / 1000 };
}

main(async () => {
  const [endpoint, certificateFile, privateKeyFile, applicationUri, pkiDir, userName, password, wrong] = process.argv.slice(2);
  const clientCertificateManager = new OPCUACertificateManager({
    rootFolder: pkiDir, automaticallyAcceptUnknownCertificate: true,
  });
  await clientCertificateManager.initialize();
  const options = { certificateFile, privateKeyFile, applicationUri, applicationName: "uacell interop", clientCertificateManager };
  const attempts = [];
  for (let i = 0; i < Number(wrong); i++) attempts.push(await attempt(endpoint, options, userName, `wrong-${i}`));
  attempts.push(await attempt(endpoint, options, userName, password));
  await done({ attempts });
});
