// OPC 10000-4's View and Attribute services as node-opcua's client uses them (decision 81):
// a Browse of the Server object two references at a time, then BrowseNext until the continuation point
// is spent (5.9.2, 5.9.3), a released continuation point used again; a Read of the NamespaceArray with
// IndexRanges (7.27); TranslateBrowsePath with no elements (5.9.4, Bad_NothingToDo); a Write of the task
// control's ExecutionMode with an IndexRange (5.11.4, Bad_WriteNotSupported). Prints what came back.
"use strict";
const { AttributeIds, BrowseDirection, DataType } = require("node-opcua-client");
const { connect, resolve, done, main, TASK_CONTROL } = require("./lib");

const browseServer = { nodeId: "i=2253", referenceTypeId: "HierarchicalReferences", includeSubtypes: true,
  browseDirection: BrowseDirection.Forward, resultMask: 63 };
const ids = (result) => result.references.map((r) => r.nodeId.toString());

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const out = {};
  session.requestedMaxReferencesPerNode = 0;
  out.whole = ids(await session.browse(browseServer));
  session.requestedMaxReferencesPerNode = 2;
  let page = await session.browse(browseServer);
  out.pages = [ids(page)];
  while (page.continuationPoint && page.continuationPoint.length) {
    page = await session.browseNext(page.continuationPoint, false);
    out.pages.push(ids(page));
  }
  page = await session.browse(browseServer);
  out.released = (await session.browseNext(page.continuationPoint, true)).statusCode.name;
  out.releasedAgain = (await session.browseNext(page.continuationPoint, false)).statusCode.name;
  session.requestedMaxReferencesPerNode = 0;

  const read = async (indexRange) => {
    const dv = await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value, indexRange });
    return { status: dv.statusCode.name, value: dv.value.value };
  };
  out.namespaces = (await read(undefined)).value;
  out.readOne = await read("1");
  out.readTwo = await read("0:1");
  out.readBeyond = await read("50:60");

  const nothing = await session.translateBrowsePath({ startingNode: "i=85", relativePath: { elements: [] } });
  out.translateEmpty = nothing.statusCode.name;

  const tc = await resolve(session, ns, "i=85", TASK_CONTROL.replace(/\/Robotics:TaskControlOperation.*$/, ""));
  const mode = await resolve(session, ns, tc, "/DI:ParameterSet/Robotics:ExecutionMode");
  const before = (await session.read({ nodeId: mode, attributeId: AttributeIds.Value })).value.value;
  const written = await session.write({
    nodeId: mode, attributeId: AttributeIds.Value, indexRange: "0",
    value: { value: { dataType: DataType.Int32, value: 2 } },
  });
  out.writeWithRange = written.name;
  out.modeUnchanged = (await session.read({ nodeId: mode, attributeId: AttributeIds.Value })).value.value === before;
  await session.close();
  await client.disconnect();
  await done(out);
});
