// Take Controller1's DI lock, see who holds it, release it (OPC 10000-100 LockingServices).
// Usage: node lock.js ENDPOINT   (an anonymous session: an operator on loopback)
"use strict";
const { OPCUAClient, AttributeIds, DataType, StatusCodes } = require("node-opcua-client");

async function lock(endpoint) {
  const client = OPCUAClient.create({ endpointMustExist: false });
  await client.connect(endpoint);
  const session = await client.createSession();
  const cell = (await session.readNamespaceArray()).indexOf("urn:uacell:cell");
  const lockNode = `ns=${cell};s=Robot1.Controllers.Controller1.Lock`;
  const read = async (name) => (await session.read({ nodeId: `${lockNode}.${name}`, attributeId: AttributeIds.Value })).value.value;
  const call = async (method, ...inputArguments) => {
    const result = await session.call({ objectId: lockNode, methodId: `${lockNode}.${method}`, inputArguments });
    if (result.statusCode !== StatusCodes.Good) throw new Error(`${method}: ${result.statusCode.name}`);
    return result.outputArguments[0].value;
  };

  console.log("InitLock:", await call("InitLock", { dataType: DataType.String, value: "cookbook" })); // 0: yours now
  console.log("Locked:", await read("Locked"));
  console.log("LockingClient:", await read("LockingClient"));
  // While it is held, other sessions' calls on the controller and its task controls answer
  // Bad_ResourceUnavailable; RenewLock before RemainingLockTime runs out keeps it.
  console.log("ExitLock:", await call("ExitLock")); // 0: released
  console.log("Locked:", await read("Locked"));
  await session.close();
  await client.disconnect();
}

lock(process.argv[2]).catch((err) => { console.error(err); process.exit(1); });
