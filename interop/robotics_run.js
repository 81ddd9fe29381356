// Power up the robot (SystemOperation GetReady), load a program by name into TaskControl1, Start it and
// collect the TransitionEvents of the task control until the program ends (ExecutingToReady), the
// AuditUpdateStateEvents of the transitions the calls caused, and the CurrentLine values published
// while the program ran (uacell's ParameterSet/CurrentLine).
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
  const fields = [
    "EventType", "SourceNode", "Transition", "Transition/Id", "FromState", "ToState", "FromState.Id", "ToState.Id",
  ];
  const item = ClientMonitoredItem.create(
    subscription,
    { nodeId: tc, attributeId: AttributeIds.EventNotifier },
    { samplingInterval: 0, discardOldest: true, queueSize: 100, filter: constructEventFilter(fields) },
    TimestampsToReturn.Neither,
  );
  let ended;
  const programEnded = new Promise((res) => { ended = res; });
  const text = (v) => (v.value ? v.value.toString() : null);
  out.audits = [];
  out.otherEvents = 0;
  item.on("changed", (values) => {
    const type = text(values[0]);
    if (type === "ns=0;i=2315") { // AuditUpdateStateEventType: its fields are asked for below
      return;
    }
    if (type !== "ns=0;i=2311") { // not a TransitionEvent
      out.otherEvents += 1;
      return;
    }
    const ev = {
      source: text(values[1]),
      transition: values[2].value ? values[2].value.text : null,
      transitionId: text(values[3]),
      from: values[4].value ? values[4].value.text : null,
      to: values[5].value ? values[5].value.text : null,
      fromId: text(values[6]),
      toId: text(values[7]),
    };
    out.events.push(ev);
    if (ev.transition === "ExecutingToReady") ended();
  });
  // The AuditUpdateStateEvents of the task control (who caused which transition).
  const auditFields = [
    "EventType", "SourceNode", "SourceName", "ClientUserId", "MethodId", "OldStateId", "NewStateId", "Status",
    "ServerId", "InputArguments", "ActionTimeStamp",
  ];
  const audits = ClientMonitoredItem.create(
    subscription,
    { nodeId: tc, attributeId: AttributeIds.EventNotifier },
    { samplingInterval: 0, discardOldest: true, queueSize: 100, filter: constructEventFilter(auditFields) },
    TimestampsToReturn.Neither,
  );
  let auditSeen = () => {};
  audits.on("changed", (values) => {
    if (text(values[0]) !== "ns=0;i=2315") return;
    out.audits.push({
      source: text(values[1]),
      sourceName: values[2].value,
      user: values[3].value === undefined ? null : values[3].value,
      method: text(values[4]),
      oldId: text(values[5]),
      newId: text(values[6]),
      status: values[7].value,
      serverId: values[8].value,
      inputs: (values[9].value || []).map((v) => (v && v.value !== undefined ? v.value : v)),
      actionTime: values[10].value ? values[10].value.toISOString() : null,
    });
    auditSeen(out.audits[out.audits.length - 1]);
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
  // uacell's CurrentLine, live while the program runs.
  const currentLine = await resolve(session, ns, params, "/DI:ParameterSet/Cell:CurrentLine");
  out.lines = [];
  const lineItem = ClientMonitoredItem.create(
    subscription,
    { nodeId: currentLine, attributeId: AttributeIds.Value },
    { samplingInterval: 0, discardOldest: true, queueSize: 100 },
    TimestampsToReturn.Neither,
  );
  lineItem.on("changed", (dv) => out.lines.push(dv.value.value));
  out.startMethod = await m(tc, "Start");
  out.start = await callStatus(session, tc, out.startMethod);
  out.stateAfterStart = await readText(session, await resolve(session, ns, tc, "/CurrentState"));
  await Promise.race([
    programEnded,
    new Promise((_, rej) => setTimeout(() => rej(new Error(`no ExecutingToReady: ${JSON.stringify(out.events)}`)), 60000)),
  ]);
  out.finalState = await readText(session, await resolve(session, ns, tc, "/CurrentState"));
  out.reason = (await session.read({
    nodeId: await resolve(session, ns, tc, "/Robotics:LastTransitionReason"), attributeId: AttributeIds.Value,
  })).value.value;
  out.readySubstate = await readText(session, await resolve(session, ns, tc, "/Robotics:ReadySubstateMachine/CurrentState"));
  out.lineAfter = (await session.read({ nodeId: currentLine, attributeId: AttributeIds.Value })).value.value;
  out.lineDataType = (await session.read({ nodeId: currentLine, attributeId: AttributeIds.DataType })).value.value.toString();
  // UnloadProgram's audit event comes after any the program's end could have caused: once it is in,
  // every audit event of the run is.
  out.unloadMethod = await m(tc, "UnloadProgram");
  const unloaded = new Promise((res) => { auditSeen = (a) => { if (a.method === out.unloadMethod) res(); }; });
  out.unload = await callStatus(session, tc, out.unloadMethod);
  await Promise.race([
    unloaded,
    new Promise((_, rej) => setTimeout(() => rej(new Error(`no audit event of UnloadProgram: ${JSON.stringify(out.audits)}`)), 30000)),
  ]);
  await subscription.terminate();
  await session.close();
  await client.disconnect();
  done(out);
});
