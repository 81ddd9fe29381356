// node-opcua as a GDS pushing a uacell server's certificate (OPC 10000-12 7.10, the push model), calling
// ServerConfiguration's methods by their NodeIds with the arguments the standard gives them.
// argv: endpoint pkiDir clientCert clientKey clientUri user password phase [phase arguments]
//   phase "request": CreateSigningRequest for a new key; prints {"request": base64 DER, "status"}
//   phase "update" certPem issuerPem trustedCaPem addPem crlFile...: UpdateCertificate, ApplyChanges, then a new
//     client that trusts only the CA (no automatic acceptance) reads ServerState; AddCertificate and
//     RemoveCertificate of addPem on the DefaultApplicationGroup's TrustList; prints the statuses and what it read
"use strict";
const crypto = require("crypto");
const fs = require("fs");
const { MessageSecurityMode, SecurityPolicy, AttributeIds, DataType, UserTokenType, makeNodeId } = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { done, main, newClient } = require("./lib");

const CONFIGURATION = "i=12637";
const GROUP = makeNodeId(14156);
const RSA_SHA256 = makeNodeId(12560);

function pemToDer(pem) {
  return Buffer.from(pem.toString("ascii").replace(/-----[^-]+-----/g, "").replace(/\s+/g, ""), "base64");
}

async function manager(dir, automatic, trusted = [], crls = []) {
  const m = new OPCUACertificateManager({ rootFolder: dir, automaticallyAcceptUnknownCertificate: automatic });
  await m.initialize();
  for (const der of trusted) await m.trustCertificate(der);
  for (const crl of crls) await m.addRevocationList(crl);
  return m;
}

async function withSession(endpoint, clientCertificateManager, cert, key, uri, user, password, work) {
  const client = newClient({
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile: cert, privateKeyFile: key, applicationUri: uri, applicationName: "uacell interop GDS",
    clientCertificateManager,
  });
  await client.connect(endpoint);
  try {
    const session = await client.createSession({ type: UserTokenType.UserName, userName: user, password });
    try {
      return await work(session);
    } finally {
      await session.close();
    }
  } finally {
    await client.disconnect();
  }
}

async function call(session, method, inputArguments) {
  const result = await session.call({ objectId: CONFIGURATION, methodId: method, inputArguments });
  return { status: result.statusCode.name, outputs: (result.outputArguments || []).map((v) => v.value) };
}

main(async () => {
  const [endpoint, pkiDir, cert, key, uri, user, password, phase, ...rest] = process.argv.slice(2);
  const gds = await manager(pkiDir, true);
  if (phase === "request") {
    const out = await withSession(endpoint, gds, cert, key, uri, user, password, (s) =>
      call(s, "i=12737", [
        { dataType: DataType.NodeId, value: GROUP },
        { dataType: DataType.NodeId, value: RSA_SHA256 },
        { dataType: DataType.String, value: "CN=uacell line 3/O=Plant" },
        { dataType: DataType.Boolean, value: true },
        { dataType: DataType.ByteString, value: crypto.randomBytes(32) },
      ]));
    done({ status: out.status, request: out.outputs[0] ? out.outputs[0].toString("base64") : null });
    return;
  }
  const [certPem, issuerPem, caPem, addPem, ...crlFiles] = rest;
  const out = await withSession(endpoint, gds, cert, key, uri, user, password, async (s) => ({
    update: await call(s, "i=13737", [
      { dataType: DataType.NodeId, value: GROUP },
      { dataType: DataType.NodeId, value: RSA_SHA256 },
      { dataType: DataType.ByteString, value: pemToDer(fs.readFileSync(certPem)) },
      { dataType: DataType.ByteString, arrayType: 1, value: [pemToDer(fs.readFileSync(issuerPem))] },
      { dataType: DataType.String, value: "" },
      { dataType: DataType.ByteString, value: Buffer.alloc(0) },
    ]),
    apply: await call(s, "i=12740", []),
    rejected: await call(s, "i=12777", []),
    added: (await s.call({ objectId: "i=12642", methodId: "i=12668", inputArguments: [
      { dataType: DataType.ByteString, value: pemToDer(fs.readFileSync(addPem)) },
      { dataType: DataType.Boolean, value: true },
    ] })).statusCode.name,
    removed: (await s.call({ objectId: "i=12642", methodId: "i=12670", inputArguments: [
      { dataType: DataType.String, value: crypto.createHash("sha1").update(pemToDer(fs.readFileSync(addPem))).digest("hex") },
      { dataType: DataType.Boolean, value: true },
    ] })).statusCode.name,
  }));
  const crls = crlFiles.map((f) => fs.readFileSync(f));
  const strict = await manager(pkiDir + "-strict", false, [pemToDer(fs.readFileSync(caPem))], crls);
  try {
    out.after = await withSession(endpoint, strict, cert, key, uri, user, password, async (s) => ({
      state: (await s.read({ nodeId: "i=2259", attributeId: AttributeIds.Value })).value.value,
    }));
  } catch (err) {
    out.after = { error: String(err.message || err) };
  }
  out.update.outputs = out.update.outputs.map(Boolean);
  out.rejected = { status: out.rejected.status, count: (out.rejected.outputs[0] || []).length };
  done(out);
});
