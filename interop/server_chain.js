// A uacell server whose certificate the plant's issuing CA issued, sent with that CA's certificate (OPC
// 10000-6 6.2.6), from node-opcua clients without automatic acceptance. node-opcua accepts a certificate
// whose direct issuer it trusts ("plant" trusts the issuing CA) and signs ActivateSession and a user
// certificate's token over the serverCertificate it was sent, the whole chain (OPC 10000-4 5.7.3.2's
// backward compatibility), which the server must accept.
// argv: endpoint trustingPkiDir emptyPkiDir caPem clientCert clientKey clientUri userCert userKey crlFile...
// (the CAs' revocation lists, DER, known to both clients)
// Prints one JSON object: "plant" (the client trusting the issuing CA): ServerState and the user certificate's role,
// "nobody" (a client that trusts no CA): the error; each with the error instead when it failed.
"use strict";
const fs = require("fs");
const { MessageSecurityMode, SecurityPolicy, AttributeIds, UserTokenType } = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { done, main, newClient, NS } = require("./lib");

async function manager(pkiDir, trusted, crls) {
  const m = new OPCUACertificateManager({ rootFolder: pkiDir, automaticallyAcceptUnknownCertificate: false });
  await m.initialize();
  for (const der of trusted) await m.trustCertificate(der);
  for (const crl of crls) await m.addRevocationList(crl);
  return m;
}

function pemToDer(pem) {
  return Buffer.from(pem.toString("ascii").replace(/-----[^-]+-----/g, "").replace(/\s+/g, ""), "base64");
}

async function session(endpoint, clientCertificateManager, certificateFile, privateKeyFile, applicationUri, user) {
  const client = newClient({
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile, privateKeyFile, applicationUri, applicationName: "uacell interop server chain",
    clientCertificateManager,
  });
  await client.connect(endpoint);
  try {
    const out = {};
    const s = await client.createSession();
    out.state = (await s.read({ nodeId: "i=2259", attributeId: AttributeIds.Value })).value.value;
    await s.close();
    const identity = { type: UserTokenType.Certificate, certificateData: pemToDer(fs.readFileSync(user.cert)), privateKey: fs.readFileSync(user.key, "ascii") };
    const u = await client.createSession(identity);
    const nsArray = (await u.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value;
    const cell = nsArray.indexOf(NS.Cell);
    out.role = (await u.read({ nodeId: `ns=${cell};s=Server.CurrentRole`, attributeId: AttributeIds.Value })).value.value;
    await u.close();
    return out;
  } finally {
    await client.disconnect();
  }
}

main(async () => {
  const [endpoint, trustingDir, emptyDir, caPem, cert, key, uri, userCert, userKey, ...crlFiles] = process.argv.slice(2);
  const user = { cert: userCert, key: userKey };
  const crls = crlFiles.map((f) => fs.readFileSync(f));
  const out = {};
  for (const [label, dir, trusted] of [["plant", trustingDir, [pemToDer(fs.readFileSync(caPem))]], ["nobody", emptyDir, []]]) {
    try {
      out[label] = await session(endpoint, await manager(dir, trusted, crls), cert, key, uri, user);
    } catch (err) {
      out[label] = { error: String(err.message || err) };
    }
  }
  done(out);
});
