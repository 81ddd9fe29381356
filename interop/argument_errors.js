// Argument errors as node-opcua sees them: missing, too many and wrong-typed input arguments, and a
// method called on an object it does not belong to. Prints each call's status code, its
// InputArgumentResults, and the task control's state before and after.
"use strict";
const { AttributeIds, DataType, Variant, VariantArrayType } = require("node-opcua-client");
const { connect, resolve, done, main, TASK_CONTROL, FILLER } = require("./lib");

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const tc = await resolve(session, ns, "i=85", TASK_CONTROL);
  const exec = await resolve(session, ns, "i=85", FILLER + "/PackML:BaseStateMachine/PackML:MachineState/PackML:ExecuteState");
  const m = async (obj, path) => resolve(session, ns, obj, path);
  const state = async () => (await session.read({
    nodeId: await m(tc, "/CurrentState"), attributeId: AttributeIds.Value,
  })).value.value.text;

  const cases = {
    missing: [tc, await m(tc, "/Robotics:LoadByName"), []],
    tooMany: [tc, await m(tc, "/Robotics:LoadByName"), [
      new Variant({ dataType: DataType.String, value: "a" }), new Variant({ dataType: DataType.String, value: "b" }),
    ]],
    wrongType: [tc, await m(tc, "/Robotics:LoadByName"), [new Variant({ dataType: DataType.Int32, value: 5 })]],
    wrongIdType: [tc, await m(tc, "/Robotics:LoadByNodeId"), [new Variant({ dataType: DataType.String, value: "x" })]],
    stopModeInt32: [tc, await m(tc, "/Robotics:Stop"), [new Variant({ dataType: DataType.Int32, value: 1 })]],
    startScalar: [exec, await m(exec, "/PackML:Start"), [new Variant({ dataType: DataType.Int32, value: 1 })]],
    startInt32Array: [exec, await m(exec, "/PackML:Start"), [new Variant({
      dataType: DataType.Int32, arrayType: VariantArrayType.Array, value: [1, 2],
    })]],
    wrongObject: [exec, await m(tc, "/Robotics:LoadByName"), [new Variant({ dataType: DataType.String, value: "p" })]],
  };
  const out = { before: await state(), results: {} };
  for (const [name, [objectId, methodId, inputArguments]] of Object.entries(cases)) {
    const res = await session.call({ objectId, methodId, inputArguments });
    out.results[name] = {
      status: res.statusCode.name,
      inputArgumentResults: (res.inputArgumentResults || []).map((s) => s.name),
    };
  }
  out.after = await state();
  await session.close();
  await client.disconnect();
  done(out);
});
