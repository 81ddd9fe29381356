// Browse the whole cell from Objects (DeviceSet and PackMLObjects), level by level, and list every
// instance of the standard part types with its browse path and DI identification where it has one.
// Usage: node cell_browse.js <endpoint>
"use strict";
const { AttributeIds, BrowseDirection, NodeClass } = require("node-opcua-client");
const { connect, resolve, done, main } = require("./lib");

const PART_TYPES = new Set([
  "MotionDeviceSystemType", "ControllerType", "TaskControlType", "MotionDeviceType", "AxisType", "PackMLBaseObjectType",
]);

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const typeNames = new Map();
  const typeName = async (nodeId) => {
    const key = nodeId.toString();
    if (!typeNames.has(key)) {
      const dv = await session.read({ nodeId, attributeId: AttributeIds.BrowseName });
      typeNames.set(key, dv.value.value.name);
    }
    return typeNames.get(key);
  };
  const roots = [
    [await resolve(session, ns, "i=85", "/DI:DeviceSet"), ""],
    [await resolve(session, ns, "i=85", "/PackML:PackMLObjects"), ""],
  ];
  const parts = [];
  const seen = new Set();
  let level = roots;
  let browsed = 0;
  while (level.length) {
    const next = [];
    for (let i = 0; i < level.length; i += 200) {
      const chunk = level.slice(i, i + 200);
      const results = await session.browse(chunk.map(([nodeId]) => ({
        nodeId, browseDirection: BrowseDirection.Forward, referenceTypeId: "i=33", includeSubtypes: true,
        nodeClassMask: NodeClass.Object, resultMask: 63,
      })));
      browsed += chunk.length;
      for (let k = 0; k < chunk.length; k++) {
        for (const ref of results[k].references || []) {
          const id = ref.nodeId.toString();
          if (ref.nodeId.namespace !== ns.Cell || seen.has(id)) continue;
          seen.add(id);
          const path = chunk[k][1] ? `${chunk[k][1]}/${ref.browseName.name}` : ref.browseName.name;
          const type = await typeName(ref.typeDefinition);
          if (PART_TYPES.has(type)) parts.push({ path, type, nodeId: id });
          next.push([id, path]);
        }
      }
    }
    level = next;
  }
  for (const part of parts) {
    if (part.type === "PackMLBaseObjectType" || part.type === "AxisType") continue;
    try {
      const serial = await resolve(session, ns, part.nodeId, "/DI:SerialNumber");
      part.serialNumber = (await session.read({ nodeId: serial, attributeId: AttributeIds.Value })).value.value;
    } catch (err) {
      part.serialNumber = null;
    }
  }
  await session.close();
  await client.disconnect();
  done({ parts, browsed });
});
