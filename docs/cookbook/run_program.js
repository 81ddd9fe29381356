// Power up Robot1, load a program by name, start it, then stop it with a stop mode the controller offers.
// Usage: node run_program.js ENDPOINT PROGRAM   (an anonymous session: an operator on loopback)
"use strict";
const { OPCUAClient, AttributeIds, DataType, VariantArrayType, StatusCodes } = require("node-opcua-client");

async function run(endpoint, program) {
  const client = OPCUAClient.create({ endpointMustExist: false });
  await client.connect(endpoint);
  const session = await client.createSession();
  const cell = (await session.readNamespaceArray()).indexOf("urn:uacell:cell");
  const controller = `ns=${cell};s=Robot1.Controllers.Controller1`; // instance NodeIds follow the browse path
  const system = `${controller}.SystemOperation.SystemOperationStateMachine`;
  const task = `${controller}.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine`;
  const read = async (nodeId) => (await session.read({ nodeId, attributeId: AttributeIds.Value })).value.value;
  const call = async (machine, method, ...inputArguments) => {
    const result = await session.call({ objectId: machine, methodId: `${machine}.${method}`, inputArguments });
    if (result.statusCode !== StatusCodes.Good) throw new Error(`${method}: ${result.statusCode.name}`);
    return result.outputArguments[0].value; // every method answers a Status (0 = OK)
  };
  const waitFor = async (machine, state) => {
    while ((await read(`${machine}.CurrentState`)).text !== state) await new Promise((r) => setTimeout(r, 50));
  };

  // PossibleStopModes: EnumValueType[], each value (Int64, node-opcua: [high, low]) a mode Stop takes.
  const modes = Object.fromEntries((await read(`${task}.PossibleStopModes`)).map((m) => [m.displayName.text, m.value[1]]));
  console.log("stop modes:", JSON.stringify(modes), "default:", await read(`${task}.ConfiguredDefaultStopMode`));

  console.log("GetReady:", await call(system, "GetReady"));
  await waitFor(system, "Ready");
  console.log("LoadByName:", await call(task, "LoadByName", { dataType: DataType.String, value: program })); // without .robot
  console.log("Start:", await call(task, "Start"));
  await waitFor(task, "Executing");
  const mode = modes.QuickStop ?? 0; // 0: the ConfiguredDefaultStopMode
  console.log("Stop:", await call(task, "Stop", { dataType: DataType.Int64, arrayType: VariantArrayType.Scalar, value: [0, mode] }));
  await waitFor(task, "Ready"); // Ready/Suspended: Start resumes, ResetToProgramStart rewinds
  console.log("UnloadProgram:", await call(task, "UnloadProgram"));
  console.log("StandDown:", await call(system, "StandDown"));
  await session.close();
  await client.disconnect();
}

run(process.argv[2], process.argv[3]).catch((err) => { console.error(err); process.exit(1); });
