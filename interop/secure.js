// Secure session from node-opcua: Basic256Sha256 SignAndEncrypt with a user name, then DI locks.
// argv: endpoint certPem keyPem applicationUri pkiDir user password
// Prints one JSON object: what the server answered.
"use strict";
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, UserTokenType, DataType,
} = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { done, main, NS } = require("./lib");

async function open(endpoint, options, identity) {
  const client = OPCUAClient.create({
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 1000 },
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    requestedSessionTimeout: 60000,
    ...options,
  });
  await client.connect(endpoint);
  try {
    const session = await client.createSession(identity);
    return { client, session };
  } catch (err) {
    await client.disconnect();
    throw err;
  }
}

main(async () => {
  const [endpoint, certificateFile, privateKeyFile, applicationUri, pkiDir, userName, password] = process.argv.slice(2);
  const clientCertificateManager = new OPCUACertificateManager({
    rootFolder: pkiDir, automaticallyAcceptUnknownCertificate: true,
  });
  await clientCertificateManager.initialize();
  const options = { certificateFile, privateKeyFile, applicationUri, applicationName: "uacell interop", clientCertificateManager };
  const out = {};

  const { client, session } = await open(endpoint, options, { type: UserTokenType.UserName, userName, password });
  out.securityMode = MessageSecurityMode[client.securityMode];
  out.securityPolicy = client.securityPolicy;
  const nsArray = (await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value;
  const cell = nsArray.indexOf(NS.Cell);
  const task = "Robot1.Controllers.Controller1.TaskControls.TaskControl1";
  const lock = `ns=${cell};s=${task}.Lock`;
  const callLock = async (method, inputArguments = []) => {
    const res = await session.call({ objectId: lock, methodId: `${lock}.${method}`, inputArguments });
    return { status: res.statusCode.name, value: res.outputArguments.length ? res.outputArguments[0].value : null };
  };
  const read = async (name) => (await session.read({ nodeId: `${lock}.${name}`, attributeId: AttributeIds.Value })).value.value;
  out.initLock = await callLock("InitLock", [{ dataType: DataType.String, value: "node-opcua" }]);
  out.locked = await read("Locked");
  out.lockingUser = await read("LockingUser");
  out.lockingClient = await read("LockingClient");
  out.breakLock = await callLock("BreakLock");
  const method = `ns=${cell};s=${task}.Lock.InitLock`;
  out.userExecutableInit = (await session.read({ nodeId: method, attributeId: AttributeIds.UserExecutable })).value.value;
  out.userExecutableBreak = (await session.read({ nodeId: `${lock}.BreakLock`, attributeId: AttributeIds.UserExecutable })).value.value;
  out.exitLock = await callLock("ExitLock");
  out.lockedAfterExit = await read("Locked");
  await session.close();
  await client.disconnect();

  try {
    const bad = await open(endpoint, options, { type: UserTokenType.UserName, userName, password: password + "x" });
    out.wrongPassword = "accepted";
    await bad.session.close();
    await bad.client.disconnect();
  } catch (err) {
    out.wrongPassword = String(err.message || err);
  }
  done(out);
});
