// Calls whose transition completes after they return (decision 38): GetReady, then a program started
// and stopped with TaskControl Stop (QuickStop), then UnloadProgram and StandDown. Collects the
// AuditUpdateStateEvents of the task control and SystemOperation state machines: the transitions
// that completed later (IdleToReady, ExecutingToReady, ReadyToIdle of SystemOperation) name the call.
// Usage: node audit_completion.js <endpoint>   (the demo cell's Robot1/Controller1/TaskControl1)
"use strict";
const {
  AttributeIds, DataType, ClientSubscription, ClientMonitoredItem, TimestampsToReturn, constructEventFilter,
} = require("node-opcua-client");
const { connect, resolve, done, main } = require("./lib");

async function callStatus(session, objectId, methodId, inputArguments = []) {
  const res = await session.call({ objectId, methodId, inputArguments });
  if (!res.statusCode.isGood()) throw new Error(`${methodId}: ${res.statusCode.toString()}`);
  return res.outputArguments.length ? res.outputArguments[0].value : null;
}

main(async () => {
  const endpoint = process.argv[2];
  const ctrl = "/DI:DeviceSet/Cell:Robot1/Robotics:Controllers/Cell:Controller1";
  const { client, session, ns } = await connect(endpoint);
  const tc = await resolve(session, ns, "i=85",
    `${ctrl}/Robotics:TaskControls/Cell:TaskControl1/Robotics:TaskControlOperation/Robotics:TaskControlStateMachine`);
  const so = await resolve(session, ns, "i=85", `${ctrl}/Robotics:SystemOperation/Robotics:SystemOperationStateMachine`);
  const m = async (obj, name) => resolve(session, ns, obj, `/Robotics:${name}`);
  const out = { audits: [], transitions: [], methods: {} };
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 1000, requestedMaxKeepAliveCount: 20,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  const fields = ["EventType", "SourceNode", "SourceName", "ClientUserId", "MethodId", "OldStateId", "NewStateId",
    "InputArguments", "Transition"];
  const text = (v) => (v.value ? v.value.toString() : null);
  const waiters = [];
  for (const [name, node] of [["tc", tc], ["so", so]]) {
    const item = ClientMonitoredItem.create(
      subscription,
      { nodeId: node, attributeId: AttributeIds.EventNotifier },
      { samplingInterval: 0, discardOldest: true, queueSize: 100, filter: constructEventFilter(fields) },
      TimestampsToReturn.Neither,
    );
    item.on("changed", (values) => {
      const type = text(values[0]);
      if (type === "ns=0;i=2311") {
        out.transitions.push({ machine: name, transition: values[8].value ? values[8].value.text : null });
      } else if (type === "ns=0;i=2315") {
        out.audits.push({
          machine: name,
          sourceName: values[2].value,
          user: values[3].value === undefined ? null : values[3].value,
          method: text(values[4]),
          oldId: text(values[5]),
          newId: text(values[6]),
          inputs: (values[7].value || []).map((v) => (v && v.value !== undefined ? v.value : v)),
        });
      } else {
        return;
      }
      for (const w of waiters.splice(0)) w();
    });
  }
  const until = async (what, pred) => {
    const deadline = Date.now() + 60000;
    while (!pred()) {
      if (Date.now() > deadline) throw new Error(`no ${what}: ${JSON.stringify(out)}`);
      await new Promise((res) => { waiters.push(res); setTimeout(res, 500); });
    }
  };
  const sawTransition = (machine, t) => () => out.transitions.some((e) => e.machine === machine && e.transition === t);
  await new Promise((res) => setTimeout(res, 300));

  for (const [obj, name] of [[so, "GetReady"], [tc, "Stop"], [so, "StandDown"], [tc, "Start"]]) {
    out.methods[name] = await m(obj, name);
  }
  await callStatus(session, so, out.methods.GetReady);
  await until("IdleToReady", sawTransition("so", "IdleToReady"));
  await callStatus(session, tc, await m(tc, "LoadByName"), [{ dataType: DataType.String, value: "gripper" }]);
  await callStatus(session, tc, await m(tc, "LoadByName"), [{ dataType: DataType.String, value: "pick_and_place" }]);
  await callStatus(session, tc, out.methods.Start);
  out.stop = await callStatus(session, tc, out.methods.Stop, [{ dataType: DataType.Int64, value: 4 }]);
  await until("ExecutingToReady", sawTransition("tc", "ExecutingToReady"));
  await callStatus(session, tc, await m(tc, "UnloadProgram"));
  await callStatus(session, so, out.methods.StandDown);
  await until("ReadyToIdle of SystemOperation", sawTransition("so", "ReadyToIdle"));
  await until("its audit event", () => out.audits.some((a) => a.machine === "so" && a.method === out.methods.StandDown));
  await subscription.terminate();
  await session.close();
  await client.disconnect();
  done(out);
});
