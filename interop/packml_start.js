// Reset Filler1, wait for Idle, call ExecuteState.Start with a PackMLDescriptorDataType[] built by node-opcua,
// wait for Execute, and read back what the server received from Status/StartParameters.
"use strict";
const { AttributeIds, DataType, VariantArrayType, NodeId, resolveNodeId } = require("node-opcua-client");
const { connect, resolve, done, main, FILLER } = require("./lib");

const CEFACT = "http://www.opcfoundation.org/UA/units/un/cefact";
// What the test asserts the server received (exactly representable as Float).
const PARAMETERS = [
  { id: 101, name: "FillVolume", unit: { namespaceUri: CEFACT, unitId: 5002584, displayName: "ml", description: "millilitre" }, value: 250.5 },
  { id: 202, name: "SealTemperature", unit: { namespaceUri: CEFACT, unitId: 4408652, displayName: "°C", description: "degree Celsius" }, value: -12.25 },
];

async function waitFor(session, nodeId, text, timeoutMs = 20000) {
  const deadline = Date.now() + timeoutMs;
  for (;;) {
    const dv = await session.read({ nodeId, attributeId: AttributeIds.Value });
    const got = dv.statusCode.isGood() && dv.value.value ? dv.value.value.text : dv.statusCode.name;
    if (got === text) return;
    if (Date.now() > deadline) throw new Error(`waited for ${text} at ${nodeId}, got ${got}`);
    await new Promise((r) => setTimeout(r, 50));
  }
}

function plainEU(eu) {
  return { namespaceUri: eu.namespaceUri, unitId: eu.unitId, displayName: eu.displayName.text, description: eu.description.text };
}

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const filler = await resolve(session, ns, "i=85", FILLER);
  const machine = await resolve(session, ns, filler, "/PackML:BaseStateMachine/PackML:MachineState");
  const execute = await resolve(session, ns, machine, "/PackML:ExecuteState");
  const out = {};

  const reset = await session.call({ objectId: machine, methodId: await resolve(session, ns, machine, "/PackML:Reset"), inputArguments: [] });
  out.reset = reset.statusCode.name;
  const executeCurrent = await resolve(session, ns, execute, "/CurrentState");
  await waitFor(session, executeCurrent, "Idle");

  const dataType = new NodeId(NodeId.NodeIdType.NUMERIC, 16, ns.PackML); // PackMLDescriptorDataType
  const eos = [];
  for (const p of PARAMETERS) {
    eos.push(await session.constructExtensionObject(dataType, {
      ID: p.id, // node-opcua keeps an all-capitals field name as is
      name: p.name,
      unit: { namespaceUri: p.unit.namespaceUri, unitId: p.unit.unitId, displayName: { text: p.unit.displayName }, description: { text: p.unit.description } },
      value: p.value,
    }));
  }
  out.sent = eos.map((e) => ({ id: e.ID, name: e.name, unit: plainEU(e.unit), value: e.value }));
  const start = await session.call({
    objectId: execute,
    methodId: await resolve(session, ns, execute, "/PackML:Start"),
    inputArguments: [{ dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: eos }],
  });
  out.start = start.statusCode.name;
  if (!start.statusCode.isGood()) throw new Error(`Start: ${start.statusCode.toString()} ${JSON.stringify(out.sent)} ${JSON.stringify(start.inputArgumentResults)}`);
  await waitFor(session, executeCurrent, "Execute");
  out.state = "Execute";

  const sp = await resolve(session, ns, filler, "/PackML:Status/Cell:StartParameters");
  const dv = await session.read({ nodeId: sp, attributeId: AttributeIds.Value });
  out.readStatus = dv.statusCode.name;
  out.received = (dv.value.value || []).map((e) => ({ id: e.ID, name: e.name, unit: plainEU(e.unit), value: e.value }));
  out.startParametersDataType = (await session.read({ nodeId: sp, attributeId: AttributeIds.DataType })).value.value.toString();
  await session.close();
  await client.disconnect();
  done(out);
});
