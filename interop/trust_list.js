// node-opcua as a GDS reading and writing a uacell server's trust list as a file (OPC 10000-12 7.8.2:
// TrustListType, a FileType holding one TrustListDataType in the OPC UA binary encoding). The structure is
// encoded and decoded by node-opcua's own TrustListDataType; the methods are called by their NodeIds.
// argv: endpoint pkiDir clientCert clientKey clientUri user password phase [phase arguments]
//   phase "read": OpenWithMasks(All), Read in pieces of 500 bytes, Close; prints the lists' SHA-1s and OpenCount
//   phase "write" caPem crlFile...: Open(Write + EraseExisting), Write the TrustedCertificates (the plant's
//     root, read first, and caPem) and TrustedCrls (the files), CloseAndUpdate; prints its status and output
"use strict";
const crypto = require("crypto");
const fs = require("fs");
const { MessageSecurityMode, SecurityPolicy, AttributeIds, DataType, UserTokenType } = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { BinaryStream } = require("node-opcua-binary-stream");
const { TrustListDataType } = require("node-opcua-types");
const { done, main, newClient } = require("./lib");

const TRUST_LIST = "i=12642";
const METHODS = {
  Open: "i=12647", Close: "i=12650", Read: "i=12652", Write: "i=12655", OpenWithMasks: "i=12663",
  CloseAndUpdate: "i=12666",
};
const OPEN_COUNT = "i=12646";

function pemToDer(pem) {
  return Buffer.from(pem.toString("ascii").replace(/-----[^-]+-----/g, "").replace(/\s+/g, ""), "base64");
}

const sha1 = (b) => crypto.createHash("sha1").update(b).digest("hex");

async function call(session, name, inputArguments) {
  const result = await session.call({ objectId: TRUST_LIST, methodId: METHODS[name], inputArguments });
  if (result.statusCode.name !== "Good") {
    const err = new Error(`${name}: ${result.statusCode.name}`);
    err.status = result.statusCode.name;
    throw err;
  }
  return (result.outputArguments || []).map((v) => v.value);
}

async function readList(session) {
  const [handle] = await call(session, "OpenWithMasks", [{ dataType: DataType.UInt32, value: 15 }]);
  const parts = [];
  for (;;) {
    const [data] = await call(session, "Read", [
      { dataType: DataType.UInt32, value: handle }, { dataType: DataType.Int32, value: 500 },
    ]);
    if (!data || data.length === 0) break;
    parts.push(data);
  }
  const openCount = (await session.read({ nodeId: OPEN_COUNT, attributeId: AttributeIds.Value })).value.value;
  await call(session, "Close", [{ dataType: DataType.UInt32, value: handle }]);
  const list = new TrustListDataType();
  list.decode(new BinaryStream(Buffer.concat(parts)));
  return { list, openCount };
}

main(async () => {
  const [endpoint, pkiDir, cert, key, uri, user, password, phase, ...rest] = process.argv.slice(2);
  const manager = new OPCUACertificateManager({ rootFolder: pkiDir, automaticallyAcceptUnknownCertificate: true });
  await manager.initialize();
  const client = newClient({
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile: cert, privateKeyFile: key, applicationUri: uri, applicationName: "uacell interop GDS",
    clientCertificateManager: manager,
  });
  await client.connect(endpoint);
  try {
    const session = await client.createSession({ type: UserTokenType.UserName, userName: user, password });
    try {
      const { list, openCount } = await readList(session);
      if (phase === "read") {
        await done({
          specifiedLists: list.specifiedLists,
          trusted: (list.trustedCertificates || []).map(sha1),
          trustedCrls: (list.trustedCrls || []).map(sha1),
          issuers: (list.issuerCertificates || []).map(sha1),
          issuerCrls: (list.issuerCrls || []).map(sha1),
          openCount,
        });
        return;
      }
      const [caPem, ...crlFiles] = rest;
      const update = new TrustListDataType({
        specifiedLists: 1 | 2, // TrustedCertificates | TrustedCrls
        trustedCertificates: [...list.trustedCertificates, pemToDer(fs.readFileSync(caPem))],
        trustedCrls: crlFiles.map((f) => fs.readFileSync(f)),
      });
      const stream = new BinaryStream(update.binaryStoreSize());
      update.encode(stream);
      const [handle] = await call(session, "Open", [{ dataType: DataType.Byte, value: 6 }]);
      for (let i = 0; i < stream.buffer.length; i += 800) {
        await call(session, "Write", [
          { dataType: DataType.UInt32, value: handle },
          { dataType: DataType.ByteString, value: stream.buffer.subarray(i, i + 800) },
        ]);
      }
      let result;
      try {
        const [applyChangesRequired] = await call(session, "CloseAndUpdate", [{ dataType: DataType.UInt32, value: handle }]);
        result = { status: "Good", applyChangesRequired };
      } catch (err) {
        if (!err.status) throw err;
        result = { status: err.status };
      }
      result.after = (await readList(session)).list.trustedCertificates.map(sha1);
      await done(result);
    } finally {
      await session.close();
    }
  } finally {
    await client.disconnect();
  }
});
