// node-opcua logged in as a user while an administrator changes that user's password with `uacell user
// passwd` (decision 99): the session reads its role (uacell's Server/CurrentRole), says it is ready by
// creating a file, then reads the role until it changes; afterwards it activates the same session again
// with the new password.
// argv: endpoint certPem keyPem applicationUri pkiDir user password readyFile newPasswordFile
// Prints {before, after, again}: the roles read (Server/CurrentRole), and users: the users the session read
// at those moments (Server/CurrentUser, decision 103; "" for anonymous).
"use strict";
const fs = require("fs");
const { OPCUAClient, UserTokenType, AttributeIds } = require("node-opcua-client");
const { done, main, NS, secureOptions } = require("./lib");

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

main(async () => {
  const [endpoint, certificateFile, privateKeyFile, applicationUri, pkiDir, userName, password, readyFile,
    newPasswordFile] = process.argv.slice(2);
  const client = OPCUAClient.create(await secureOptions(certificateFile, privateKeyFile, applicationUri, pkiDir));
  await client.connect(endpoint);
  try {
    const session = await client.createSession({ type: UserTokenType.UserName, userName, password });
    const namespaces = (await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value;
    const roleNode = `ns=${namespaces.indexOf(NS.Cell)};s=Server.CurrentRole`;
    const role = async () => (await session.read({ nodeId: roleNode, attributeId: AttributeIds.Value })).value.value;
    const userNode = `ns=${namespaces.indexOf(NS.Cell)};s=Server.CurrentUser`;
    const user = async () => (await session.read({ nodeId: userNode, attributeId: AttributeIds.Value })).value.value;
    const users = [await user()];
    const before = await role();
    fs.writeFileSync(readyFile, "ready");
    let after = before;
    for (let waited = 0; after === before && waited < 20000; waited += 100) {
      await sleep(100);
      after = await role();
    }
    users.push(await user());
    const newPassword = fs.readFileSync(newPasswordFile, "utf8").trim();
    await client.changeSessionIdentity(session, { type: UserTokenType.UserName, userName, password: newPassword });
    const again = await role();
    users.push(await user());
    await session.close();
    await done({ before, after, again, users });
  } finally {
    await client.disconnect();
  }
});
