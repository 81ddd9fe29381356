// What a client that knows only OPC 40001-1 (Machinery) sees: the Machines folder found below Objects
// by its BrowseName in the Machinery namespace (looked up by URI), every machine it organizes, each
// machine's Identification (every property and its value) and the CurrentState (text and Number) of
// its MachineryItemState and MachineryOperationMode in MachineryBuildingBlocks.
// Usage: node machines.js <endpoint>
"use strict";
const { AttributeIds, BrowseDirection, makeBrowsePath, StatusCodes } = require("node-opcua-client");
const { connect, done, main } = require("./lib");

const MACHINERY = "http://opcfoundation.org/UA/Machinery/";
const DI = "http://opcfoundation.org/UA/DI/";
const ORGANIZES = "i=35";
const HAS_PROPERTY = "i=46";

main(async () => {
  const endpoint = process.argv[2];
  const { client, session } = await connect(endpoint);
  const nsArray = (await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value;
  const m = nsArray.indexOf(MACHINERY);
  const di = nsArray.indexOf(DI);
  if (m < 0) throw new Error("the server has no Machinery namespace");
  const forward = async (nodeId, referenceTypeId) =>
    (await session.browse({ nodeId, browseDirection: BrowseDirection.Forward, referenceTypeId,
      includeSubtypes: true, resultMask: 63 })).references || [];
  const folder = (await forward("i=85", ORGANIZES))
    .find((r) => r.browseName.namespaceIndex === m && r.browseName.name === "Machines");
  if (!folder) throw new Error("no Machines folder in Objects");
  const target = async (start, path) => {
    const result = await session.translateBrowsePath(makeBrowsePath(start, path));
    if (!result.statusCode.equals(StatusCodes.Good)) return null;
    return result.targets[0].targetId.toString();
  };
  const text = (v) => (v && typeof v === "object" && "text" in v ? v.text : v);
  const plain = (v) => (v instanceof Date ? v.toISOString() : typeof v === "bigint" ? Number(v) : text(v));
  const machines = {};
  for (const machine of await forward(folder.nodeId, ORGANIZES)) {
    const id = machine.nodeId.toString();
    const identification = {};
    const ident = await target(id, `/${di}:Identification`);
    for (const p of ident ? await forward(ident, HAS_PROPERTY) : []) {
      const dv = await session.read({ nodeId: p.nodeId, attributeId: AttributeIds.Value });
      identification[p.browseName.name] = plain(dv.value.value);
    }
    const state = async (name) => {
      const current = await target(id, `/${m}:MachineryBuildingBlocks/${m}:${name}/0:CurrentState`);
      const number = await target(id, `/${m}:MachineryBuildingBlocks/${m}:${name}/0:CurrentState.0:Number`);
      if (!current) return null;
      const [c, n] = await session.read([current, number].map((nodeId) => ({ nodeId, attributeId: AttributeIds.Value })));
      return [text(c.value.value), n.value.value];
    };
    machines[machine.browseName.name] = {
      identification,
      itemState: await state("MachineryItemState"),
      operationMode: await state("MachineryOperationMode"),
    };
  }
  await session.close();
  await client.disconnect();
  await done({ machines });
});
