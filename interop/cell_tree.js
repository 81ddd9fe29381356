// Walk the cell's instances below DeviceSet and PackMLObjects (the cell's namespace only) and print
// each node as namespace-independent data: NodeClass, BrowseName, DisplayName, every reference (both
// directions, every type, targets as namespace URI + identifier), the variables' DataType, ValueRank,
// ArrayDimensions and AccessLevel, the methods' InputArguments/OutputArguments values and the DI
// identification texts.
// The entries of a file directory (what a FileDirectoryType instance organizes) are its contents,
// not the model: they are neither walked nor listed.
// Usage: node cell_tree.js <endpoint>
"use strict";
const { AttributeIds, BrowseDirection, NodeClass, resolveNodeId } = require("node-opcua-client");
const { connect, resolve, done, main } = require("./lib");

const HIERARCHICAL = "i=33";
const FILE_DIRECTORY_TYPE = "i=13353";
const ORGANIZES = "i=35";
const HAS_TYPE_DEFINITION = "i=40";

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const nsArray = (await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value;
  // A NodeId as "<namespace URI>;<identifier>" (the base namespace keeps its short form).
  const key = (nodeId) => {
    const id = resolveNodeId(nodeId);
    const text = id.toString().replace(/^ns=\d+;/, "");
    return id.namespace === 0 ? text : `${nsArray[id.namespace]};${text}`;
  };
  const qname = (q) => `${q.namespaceIndex ? nsArray[q.namespaceIndex] : ""}:${q.name}`;

  const browseAll = async (nodeIds, spec) => {
    const out = [];
    for (let i = 0; i < nodeIds.length; i += 200) {
      const chunk = nodeIds.slice(i, i + 200);
      const results = await session.browse(chunk.map((nodeId) => ({ nodeId, resultMask: 63, ...spec })));
      for (const r of results) {
        let refs = r.references || [];
        let cp = r.continuationPoint;
        while (cp && cp.length) {
          const more = await session.browseNext(cp, false);
          refs = refs.concat(more.references || []);
          cp = more.continuationPoint;
        }
        out.push(refs);
      }
    }
    return out;
  };
  const readAll = async (items) => {
    const out = [];
    for (let i = 0; i < items.length; i += 500) out.push(...(await session.read(items.slice(i, i + 500))));
    return out;
  };

  const roots = [
    await resolve(session, ns, "i=85", "/DI:DeviceSet"),
    await resolve(session, ns, "i=85", "/PackML:PackMLObjects"),
  ];
  const nodes = new Map();
  let level = roots;
  const seen = new Set(roots);
  while (level.length) {
    const all = await browseAll(level, { browseDirection: BrowseDirection.Both, referenceTypeId: "i=31", includeSubtypes: true });
    const down = await browseAll(level, { browseDirection: BrowseDirection.Forward, referenceTypeId: HIERARCHICAL, includeSubtypes: true });
    const next = [];
    for (let k = 0; k < level.length; k++) {
      const nodeId = level[k];
      const isRoot = roots.includes(nodeId);
      const directory = all[k].some((r) => r.isForward && key(r.referenceTypeId) === HAS_TYPE_DEFINITION
        && key(r.nodeId) === FILE_DIRECTORY_TYPE);
      const entry = (r) => directory && r.isForward && key(r.referenceTypeId) === ORGANIZES;
      if (!isRoot) {
        nodes.set(nodeId, {
          references: all[k].filter((r) => !entry(r))
            .map((r) => [key(r.referenceTypeId), r.isForward, key(r.nodeId)])
            .sort((a, b) => JSON.stringify(a).localeCompare(JSON.stringify(b))),
        });
      }
      for (const r of down[k]) {
        const id = r.nodeId.toString();
        if (r.nodeId.namespace !== ns.Cell || seen.has(id) || entry(r)) continue;
        seen.add(id);
        next.push(id);
      }
    }
    level = next;
  }

  const ids = [...nodes.keys()];
  const attrs = ["NodeClass", "BrowseName", "DisplayName", "DataType", "ValueRank", "ArrayDimensions", "AccessLevel"];
  const values = await readAll(ids.flatMap((nodeId) => attrs.map((a) => ({ nodeId, attributeId: AttributeIds[a] }))));
  const out = {};
  ids.forEach((nodeId, i) => {
    const v = (a) => values[i * attrs.length + attrs.indexOf(a)];
    const node = nodes.get(nodeId);
    const nodeClass = NodeClass[v("NodeClass").value.value];
    const entry = {
      nodeClass,
      browseName: qname(v("BrowseName").value.value),
      displayName: v("DisplayName").value.value.text,
      references: node.references,
    };
    if (nodeClass === "Variable") {
      entry.dataType = key(v("DataType").value.value);
      entry.valueRank = v("ValueRank").value.value;
      const dims = v("ArrayDimensions").value.value;
      // Unknown lengths: no ArrayDimensions, an empty array and zeros all say the same (OPC 10000-3, 5.6.2).
      entry.arrayDimensions = dims && Array.from(dims).some((d) => d !== 0) ? Array.from(dims) : [];
      entry.accessLevel = v("AccessLevel").value.value;
    }
    out[key(nodeId)] = entry;
  });
  // The methods' arguments: the values of their InputArguments/OutputArguments properties.
  const argumentNodes = ids.filter((id) => /^(InputArguments|OutputArguments)$/.test(out[key(id)].browseName.slice(1)));
  const argValues = await readAll(argumentNodes.map((nodeId) => ({ nodeId, attributeId: AttributeIds.Value })));
  argumentNodes.forEach((nodeId, i) => {
    const args = argValues[i].value.value || [];
    out[key(nodeId)].arguments = Array.from(args).map((a) => ({
      name: a.name,
      dataType: key(a.dataType),
      valueRank: a.valueRank,
      arrayDimensions: a.arrayDimensions ? Array.from(a.arrayDimensions) : [],
      description: a.description ? a.description.text : null,
    }));
  });
  // The DI identification values (Manufacturer, Model, SerialNumber, ...): texts the cell configures.
  const diUri = "http://opcfoundation.org/UA/DI/";
  const identification = ids.filter((id) => out[key(id)].nodeClass === "Variable"
    && out[key(id)].browseName.startsWith(`${diUri}:`) && ["i=12", "i=21"].includes(out[key(id)].dataType));
  const texts = await readAll(identification.map((nodeId) => ({ nodeId, attributeId: AttributeIds.Value })));
  identification.forEach((nodeId, i) => {
    // Unset (null) reads as "": a NodeSet has no way to say null but leaving the Value out, and a
    // loader then gives the variable its own default (node-opcua: the empty string).
    const v = texts[i].value.value;
    out[key(nodeId)].value = (v && typeof v === "object" ? v.text : v) || "";
  });
  await session.close();
  await client.disconnect();
  await done({ nodes: out });
});
