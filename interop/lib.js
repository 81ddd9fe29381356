// Shared helpers for uacell's interoperability scripts (node-opcua-client).
// Each script takes the endpoint as its first argument and prints one JSON object as its last line.
"use strict";
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, makeBrowsePath, StatusCodes,
} = require("node-opcua-client");

const NS = {
  DI: "http://opcfoundation.org/UA/DI/",
  Robotics: "http://opcfoundation.org/UA/Robotics/",
  PackML: "http://opcfoundation.org/UA/PackML/",
  Cell: "urn:uacell:cell",
};

// A client that tries once, with a 60 s session timeout; SecurityPolicy None unless options say otherwise.
function newClient(options = {}) {
  return OPCUAClient.create({
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 1000 },
    securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None,
    requestedSessionTimeout: 60000,
    ...options,
  });
}

async function connect(endpoint, { securityMode, securityPolicy, userIdentity, certificateFile, privateKeyFile } = {}) {
  const client = OPCUAClient.create({
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 2, initialDelay: 200, maxDelay: 1000 },
    securityMode: securityMode || MessageSecurityMode.None,
    securityPolicy: securityPolicy || SecurityPolicy.None,
    certificateFile, privateKeyFile,
    requestedSessionTimeout: 60000,
  });
  await client.connect(endpoint);
  const session = await client.createSession(userIdentity);
  const nsArray = (await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value;
  const ns = {};
  for (const [key, uri] of Object.entries(NS)) ns[key] = nsArray.indexOf(uri);
  return { client, session, ns };
}

// Options for a client over Basic256Sha256 SignAndEncrypt with the application certificate a test made (PEM
// files), node-opcua's own PKI in pkiDir accepting the server's certificate; tries once.
async function secureOptions(certificateFile, privateKeyFile, applicationUri, pkiDir) {
  const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
  const clientCertificateManager = new OPCUACertificateManager({ rootFolder: pkiDir, automaticallyAcceptUnknownCertificate: true });
  await clientCertificateManager.initialize();
  return {
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 200, maxDelay: 1000 },
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile, privateKeyFile, applicationUri, applicationName: "uacell interop", clientCertificateManager,
  };
}

// A session of user/password subscribed to the Server object's events with the select clauses `fields`;
// onEvent(values) is called with each event's field values. Returns { client, session }.
async function serverEvents(endpoint, userName, password, fields, onEvent) {
  const {
    ClientSubscription, ClientMonitoredItem, TimestampsToReturn, UserTokenType, constructEventFilter,
  } = require("node-opcua-client");
  const client = newClient();
  await client.connect(endpoint);
  const session = await client.createSession({ type: UserTokenType.UserName, userName, password });
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 1000, requestedMaxKeepAliveCount: 20,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  const item = ClientMonitoredItem.create(
    subscription,
    { nodeId: "i=2253", attributeId: AttributeIds.EventNotifier },
    { samplingInterval: 0, discardOldest: true, queueSize: 100, filter: constructEventFilter(fields) },
    TimestampsToReturn.Neither,
  );
  item.on("changed", onEvent);
  return { client, session };
}

// path: "/<ns>:Name/<ns>:Name" with keys of NS instead of indexes, e.g. "/Cell:Robot1/Robotics:Controllers"
async function resolve(session, ns, startNodeId, path) {
  const concrete = path.replace(/(\w+):/g, (m, key) => (key in ns ? `${ns[key]}:` : m));
  const result = await session.translateBrowsePath(makeBrowsePath(startNodeId, concrete));
  if (!result.statusCode.equals(StatusCodes.Good) || !result.targets.length) {
    throw new Error(`cannot resolve ${path}: ${result.statusCode.toString()}`);
  }
  return result.targets[0].targetId.toString();
}

// Resolves once the line is written: await it before exiting when the output is large (a pipe).
function done(obj) {
  return new Promise((resolve) => process.stdout.write(JSON.stringify(obj) + "\n", resolve));
}

async function main(fn) {
  try {
    await fn();
    process.exit(0);
  } catch (err) {
    console.error(err && err.stack ? err.stack : String(err));
    process.exit(1);
  }
}

const TASK_CONTROL = "/DI:DeviceSet/Cell:Robot1/Robotics:Controllers/Cell:Controller1/Robotics:TaskControls" +
  "/Cell:TaskControl1/Robotics:TaskControlOperation/Robotics:TaskControlStateMachine";
const SYSTEM_OPERATION = "/DI:DeviceSet/Cell:Robot1/Robotics:Controllers/Cell:Controller1" +
  "/Robotics:SystemOperation/Robotics:SystemOperationStateMachine";
const FILLER = "/PackML:PackMLObjects/Cell:Filler1";

module.exports = { connect, newClient, secureOptions, serverEvents, resolve, done, main, NS, TASK_CONTROL, SYSTEM_OPERATION, FILLER };
