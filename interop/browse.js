// Browse from Objects to TaskControl1's state machine and Filler1's ExecuteState; read method arguments.
"use strict";
const { AttributeIds, BrowseDirection } = require("node-opcua-client");
const { connect, resolve, done, main, TASK_CONTROL, FILLER } = require("./lib");

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const out = { namespaces: ns };
  // Walk by Browse (not only TranslateBrowsePath) to prove the hierarchy is browsable step by step.
  const steps = TASK_CONTROL.split("/").filter(Boolean);
  let node = "i=85";
  const walked = [];
  for (const step of steps) {
    const [key, name] = step.split(":");
    const res = await session.browse({ nodeId: node, browseDirection: BrowseDirection.Forward, resultMask: 63 });
    const hit = res.references.find((r) => r.browseName.name === name && r.browseName.namespaceIndex === ns[key]);
    if (!hit) throw new Error(`no ${step} below ${node}`);
    walked.push(name);
    node = hit.nodeId.toString();
  }
  out.walked = walked;
  const tcsm = node;
  const loadArgs = await resolve(session, ns, tcsm, "/Robotics:LoadByNodeId/InputArguments");
  const args = (await session.read({ nodeId: loadArgs, attributeId: AttributeIds.Value })).value.value;
  out.loadByNodeId = args.map((a) => ({ name: a.name, dataType: a.dataType.toString(), valueRank: a.valueRank }));
  const exec = await resolve(session, ns, "i=85", FILLER + "/PackML:BaseStateMachine/PackML:MachineState/PackML:ExecuteState");
  const startArgs = await resolve(session, ns, exec, "/PackML:Start/InputArguments");
  const sargs = (await session.read({ nodeId: startArgs, attributeId: AttributeIds.Value })).value.value;
  out.start = sargs.map((a) => ({ name: a.name, dataType: a.dataType.toString(), valueRank: a.valueRank }));
  out.executeStateType = (await session.browse({ nodeId: exec, browseDirection: BrowseDirection.Forward, resultMask: 63 }))
    .references.filter((r) => r.referenceTypeId.toString() === "ns=0;i=40").map((r) => r.nodeId.toString());
  await session.close();
  await client.disconnect();
  done(out);
});
