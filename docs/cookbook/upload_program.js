// Upload a robot program into Controller1's Programs folder, as an engineer (OPC 10000-5 FileDirectoryType).
// Usage: node upload_program.js ENDPOINT USER PASSWORD FILE
"use strict";
const fs = require("fs");
const path = require("path");
const { OPCUAClient, UserTokenType, DataType, StatusCodes } = require("node-opcua-client");

const WRITE = 2, ERASE_EXISTING = 4; // Open's mode bits
const CHUNK = 64 * 1024; // every Write request stays well below [limits] max_message_size (256 KiB)

async function call(session, objectId, methodId, ...inputArguments) {
  const result = await session.call({ objectId, methodId, inputArguments });
  if (result.statusCode !== StatusCodes.Good) throw new Error(`${methodId}: ${result.statusCode.name}`);
  return result.outputArguments.map((v) => v.value);
}

async function upload(endpoint, userName, password, file) {
  const client = OPCUAClient.create({ endpointMustExist: false });
  await client.connect(endpoint);
  // the password travels encrypted, even on the None endpoint
  const session = await client.createSession({ type: UserTokenType.UserName, userName, password });
  const cell = (await session.readNamespaceArray()).indexOf("urn:uacell:cell");
  const programs = `ns=${cell};s=Robot1.Controllers.Controller1.Programs`;
  const name = path.basename(file);
  const existing = (await session.browse(programs)).references.find((r) => r.browseName.name === name);
  const fileId = existing // a file of that name: replace its content; else create it (empty, not opened)
    ? existing.nodeId
    : (await call(session, programs, `${programs}.CreateFile`,
      { dataType: DataType.String, value: name }, { dataType: DataType.Boolean, value: false }))[0];
  const method = async (m) => (await session.translateBrowsePath({
    startingNode: fileId, relativePath: { elements: [{ targetName: { namespaceIndex: 0, name: m } }] },
  })).targets[0].targetId;
  const [handle] = await call(session, fileId, await method("Open"), { dataType: DataType.Byte, value: WRITE | ERASE_EXISTING });
  const data = fs.readFileSync(file);
  const write = await method("Write");
  for (let start = 0; start < data.length; start += CHUNK) {
    await call(session, fileId, write, { dataType: DataType.UInt32, value: handle },
      { dataType: DataType.ByteString, value: data.subarray(start, start + CHUNK) });
  }
  await call(session, fileId, await method("Close"), { dataType: DataType.UInt32, value: handle }); // the new content counts now
  console.log(`uploaded ${name}: ${data.length} bytes`);
  await session.close();
  await client.disconnect();
}

const [endpoint, user, password, file] = process.argv.slice(2);
upload(endpoint, user, password, file).catch((err) => { console.error(err); process.exit(1); });
