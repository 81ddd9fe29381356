// Reset Filler1, Start it with two parameters (PackMLDescriptorDataType[]), read back what it accepted, Stop.
// Usage: node packml_start.js ENDPOINT   (an anonymous session: an operator on loopback)
"use strict";
const { OPCUAClient, AttributeIds, DataType, VariantArrayType, StatusCodes, resolveNodeId } = require("node-opcua-client");

async function start(endpoint) {
  const client = OPCUAClient.create({ endpointMustExist: false });
  await client.connect(endpoint);
  const session = await client.createSession();
  const namespaces = await session.readNamespaceArray();
  const cell = namespaces.indexOf("urn:uacell:cell");
  const pml = namespaces.indexOf("http://opcfoundation.org/UA/PackML/");
  const machine = `ns=${cell};s=Filler1.BaseStateMachine.MachineState`;
  const execute = `${machine}.ExecuteState`;
  const read = async (nodeId) => (await session.read({ nodeId, attributeId: AttributeIds.Value })).value.value;
  const call = async (object, method, ...inputArguments) => {
    const result = await session.call({ objectId: object, methodId: `${object}.${method}`, inputArguments });
    console.log(`${method}:`, result.statusCode.name);
    if (result.statusCode !== StatusCodes.Good) throw new Error(JSON.stringify(result.inputArgumentResults));
  };
  const waitFor = async (state) => {
    while ((await read(`${execute}.CurrentState`)).text !== state) await new Promise((r) => setTimeout(r, 50));
  };

  await call(machine, "Reset"); // Stopped -> Resetting -> Idle
  await waitFor("Idle");
  const descriptor = resolveNodeId(`ns=${pml};i=16`); // PackMLDescriptorDataType
  const parameters = await Promise.all([
    // node-opcua keeps the all-capitals field ID as is and lower-cases the first letter of the others
    { ID: 101, name: "FillVolume", unit: { displayName: { text: "ml" } }, value: 250.5 },
    { ID: 102, name: "CapTorque", unit: { displayName: { text: "N.m" } }, value: 2.25 },
  ].map((p) => session.constructExtensionObject(descriptor, p)));
  await call(execute, "Start", { dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: parameters });
  await waitFor("Execute");
  const accepted = await read(`ns=${cell};s=Filler1.Status.StartParameters`);
  console.log("accepted:", accepted.map((p) => [p.ID, p.name, p.value]));
  await call(machine, "Stop");
  await session.close();
  await client.disconnect();
}

start(process.argv[2]).catch((err) => { console.error(err); process.exit(1); });
