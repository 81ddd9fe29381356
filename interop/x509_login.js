// X.509 user certificates from node-opcua (OPC 10000-4 7.41.5): logins on a SecurityPolicy None channel,
// where the user token policy names the policy to sign with, and a session changing its user.
// argv: endpoint then, per user, label certDer keyPem (the user's certificate and private key)
// Prints one JSON object: per label, the role the session reads in Server/CurrentRole or the error;
// and "changeUser": the status of an anonymous session's change to the first user, and its role after.
"use strict";
const fs = require("fs");
const { OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, UserTokenType } = require("node-opcua-client");
const { done, main, NS } = require("./lib");

function identity(certFile, keyFile) {
  return {
    type: UserTokenType.Certificate,
    certificateData: fs.readFileSync(certFile),
    privateKey: fs.readFileSync(keyFile, "ascii"),
  };
}

async function role(session) {
  const nsArray = (await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value;
  const cell = nsArray.indexOf(NS.Cell);
  return (await session.read({ nodeId: `ns=${cell};s=Server.CurrentRole`, attributeId: AttributeIds.Value })).value.value;
}

main(async () => {
  const [endpoint, ...rest] = process.argv.slice(2);
  const users = [];
  for (let i = 0; i + 2 < rest.length; i += 3) users.push({ label: rest[i], cert: rest[i + 1], key: rest[i + 2] });
  const client = OPCUAClient.create({
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 1000 },
    securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None,
    requestedSessionTimeout: 60000,
  });
  await client.connect(endpoint);
  const out = {};
  try {
    for (const user of users) {
      try {
        const session = await client.createSession(identity(user.cert, user.key));
        out[user.label] = { role: await role(session) };
        await session.close();
      } catch (err) {
        out[user.label] = { error: String(err.message || err) };
      }
    }
    const session = await client.createSession();
    const before = await role(session);
    const status = await session.changeUser(identity(users[0].cert, users[0].key));
    out.changeUser = { before, status: status.name, after: await role(session) };
    await session.close();
  } finally {
    await client.disconnect();
  }
  done(out);
});
