// Alarm methods from node-opcua: AddComment, Disable, Enable on Controller1's EmergencyStop condition,
// called by the ConditionType's method NodeIds as alarm clients do. argv: endpoint
"use strict";
const { AttributeIds, DataType } = require("node-opcua-client");
const { connect, done, main } = require("./lib");

const ENABLE = "i=9027";
const DISABLE = "i=9028";
const ADD_COMMENT = "i=9029";

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const cond = `ns=${ns.Cell};s=Robot1.Controllers.Controller1.SystemOperation.Conditions.EmergencyStop`;
  const read = async (path) => (await session.read({ nodeId: `${cond}.${path}`, attributeId: AttributeIds.Value })).value.value;
  const call = async (methodId, inputArguments = []) => (await session.call({ objectId: cond, methodId, inputArguments })).statusCode.name;
  const out = {};
  const eventId = await read("EventId");
  const comment = { dataType: DataType.LocalizedText, value: { text: "from node-opcua" } };
  out.addCommentUnknown = await call(ADD_COMMENT, [{ dataType: DataType.ByteString, value: Buffer.from("nope") }, comment]);
  out.addComment = await call(ADD_COMMENT, [{ dataType: DataType.ByteString, value: eventId }, comment]);
  const waitFor = async (path, expected) => {
    const deadline = Date.now() + 20000;
    for (;;) {
      const v = await read(path);
      const got = v && v.text !== undefined ? v.text : v;
      if (got === expected) return got;
      if (Date.now() > deadline) throw new Error(`${path}: ${got}, expected ${expected}`);
      await new Promise((r) => setTimeout(r, 50));
    }
  };
  out.comment = await waitFor("Comment", "from node-opcua");
  out.disable = await call(DISABLE);
  out.enabledAfterDisable = await waitFor("EnabledState.Id", false);
  out.disableAgain = await call(DISABLE);
  out.addCommentDisabled = await call(ADD_COMMENT, [{ dataType: DataType.ByteString, value: await read("EventId") }, comment]);
  out.enable = await call(ENABLE);
  out.enabledAfterEnable = await waitFor("EnabledState.Id", true);
  out.enableAgain = await call(ENABLE);
  await session.close();
  await client.disconnect();
  done(out);
});
