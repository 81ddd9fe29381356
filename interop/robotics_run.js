// Power up the robot (SystemOperation GetReady), load a program by name into TaskControl1, Start it and
// collect the TransitionEvents of the task control until the program ends (ExecutingToReady).
// Usage: node robotics_run.js <endpoint> [programName [robot controller taskControl]]
// (default: the demo cell's Robot1/Controller1/TaskControl1)
"use strict";
const {
  AttributeIds, DataType, ClientSubscription, ClientMonitoredItem, TimestampsToReturn, constructEventFilter,
} = require("node-opcua-client");
const { connect, resolve, done, main } = require("./lib");

async function readText(session, nodeId) {
  const dv = await session.read({ nodeId, attributeId: AttributeIds.Value });
  return dv.statusCode.isGood() && dv.value.value ? dv.value.value.text : dv.statusCode.name;
}

async function waitFor(session, nodeId, text, timeoutMs = 30000) {
  const deadline = Date.now() + timeoutMs;
  for (;;) {
    const got = await readText(session, nodeId);
    if (got === text) return;
    if (Date.now() > deadline) throw new Error(`waited for ${text} at ${nodeId}, got ${got}`);
    await new Promise((r) => setTimeout(r, 50));
  }
}

async function callStatus(session, objectId, methodId, inputArguments = []) {
  const res = await session.call({ objectId, methodId, inputArguments });
  if (!res.statusCode.isGood()) throw new Error(`${methodId}: ${res.statusCode.toString()}`);
  return res.outputArguments[0].value;
}

main(async () => {
  const endpoint = process.argv[2];
  const program = process.argv[3] || "pick_and_place";
  const [robot, controller, task] = process.argv.slice(4, 7);
  const ctrl = `/DI:DeviceSet/Cell:${robot || "Robot1"}/Robotics:Controllers/Cell:${controller || "Controller1"}`;
  const taskControl = `${ctrl}/Robotics:TaskControls/Cell:${task || "TaskControl1"}`;
  const { client, session, ns } = await connect(endpoint);
  const tc = await resolve(session, ns, "i=85", `${taskControl}/Robotics:TaskControlOperation/Robotics:TaskControlStateMachine`);
  const so = await resolve(session, ns, "i=85", `${ctrl}/Robotics:SystemOperation/Robotics:SystemOperationStateMachine`);
  const m = async (obj, name) => resolve(session, ns, obj, `/Robotics:${name}`);
  const out = { events: [] };

  // TransitionEvents of the task control: Transition, FromState, ToState (+ the Ids)
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 1000, requestedMaxKeepAliveCount: 20,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  const fields = ["EventType", "SourceNode", "Transition", "Transition/Id", "FromState", "ToState"];
  const item = ClientMonitoredItem.create(
    subscription,
    { nodeId: tc, attributeId: AttributeIds.EventNotifier },
    { samplingInterval: 0, discardOldest: true, queueSize: 100, filter: constructEventFilter(fields) },
    TimestampsToReturn.Neither,
  );
  let ended;
  const programEnded = new Promise((res) => { ended = res; });
  item.on("changed", (values) => {
    const ev = {
      source: values[1].value ? values[1].value.toString() : null,
      transition: values[2].value ? values[2].value.text : null,
      transitionId: values[3].value ? values[3].value.toString() : null,
      from: values[4].value ? values[4].value.text : null,
      to: values[5].value ? values[5].value.text : null,
    };
    out.events.push(ev);
    if (ev.transition === "ExecutingToReady") ended();
  });
  await new Promise((res) => setTimeout(res, 300));

  out.getReady = await callStatus(session, so, await m(so, "GetReady"));
  await waitFor(session, await resolve(session, ns, so, "/CurrentState"), "Ready");
  out.systemState = "Ready";

  out.loadGripper = await callStatus(session, tc, await m(tc, "LoadByName"), [{ dataType: DataType.String, value: "gripper" }]);
  out.load = await callStatus(session, tc, await m(tc, "LoadByName"), [{ dataType: DataType.String, value: program }]);
  const params = await resolve(session, ns, "i=85", taskControl);
  out.programName = (await session.read({
    nodeId: await resolve(session, ns, params, "/DI:ParameterSet/Robotics:TaskProgramName"), attributeId: AttributeIds.Value,
  })).value.value;
  out.start = await callStatus(session, tc, await m(tc, "Start"));
  await Promise.race([
    programEnded,
    new Promise((_, rej) => setTimeout(() => rej(new Error(`no ExecutingToReady: ${JSON.stringify(out.events)}`)), 60000)),
  ]);
  out.finalState = await readText(session, await resolve(session, ns, tc, "/CurrentState"));
  out.reason = (await session.read({
    nodeId: await resolve(session, ns, tc, "/Robotics:LastTransitionReason"), attributeId: AttributeIds.Value,
  })).value.value;
  out.readySubstate = await readText(session, await resolve(session, ns, tc, "/Robotics:ReadySubstateMachine/CurrentState"));
  await subscription.terminate();
  await session.close();
  await client.disconnect();
  done(out);
});
