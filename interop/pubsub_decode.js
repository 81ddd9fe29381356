// PubSub JSON messages decoded by node-opcua's own OPC 10000-6 v1.05 JSON decoder (node-opcua-json),
// as a generic subscriber would: the field's BuiltInType comes from the writer's ua-metadata (OPC
// 10000-14 §7.2.5.4.2: the VerboseEncoding collapses Variants of concrete DataTypes), the rest from the
// JSON. Structures are left out (decoding them needs the DataType's constructor).
// argv: a JSON file holding [{topic, payload}] in arrival order (payload: the message text, "" for a clear)
"use strict";
const fs = require("fs");

async function run() {
  const json = await import("node-opcua-json/105");
  const messages = JSON.parse(fs.readFileSync(process.argv[2], "utf8"));
  const namespaces = ["http://opcfoundation.org/UA/"];
  const fields = new Map(); // "<PublisherId>/<DataSetWriterId>" -> Map(name -> FieldMetaData)
  const builder = {
    getExtensionObjectConstructor() {
      throw new Error("no structure constructors in this decoder");
    },
  };
  const decoded = [];
  const errors = [];
  for (const { topic, payload } of messages) {
    if (!payload) continue;
    const body = JSON.parse(payload);
    if (body.MessageType === "ua-metadata") {
      for (const uri of body.MetaData.Namespaces || []) if (!namespaces.includes(uri)) namespaces.push(uri);
      const byName = new Map();
      for (const f of body.MetaData.Fields) byName.set(f.Name, f);
      fields.set(`${body.PublisherId}/${body.DataSetWriterId}`, byName);
      continue;
    }
    if (body.MessageType !== "ua-data") continue;
    for (const m of body.Messages) {
      const meta = fields.get(`${body.PublisherId}/${m.DataSetWriterId}`);
      for (const [name, field] of Object.entries(m.Payload || {})) {
        const fmd = meta && meta.get(name);
        if (!fmd || fmd.BuiltInType === 22) continue;
        try {
          const dataValue = field !== null && typeof field === "object" && "Value" in field;
          const pojo = dataValue ? { ...field } : { Value: field };
          if (!("UaType" in pojo) && pojo.Value !== null) pojo.UaType = fmd.BuiltInType;
          let status = "Good";
          let variant;
          let time = null;
          if (dataValue) {
            const dv = json.opcuaJsonDecodeDataValue(pojo, builder, namespaces);
            status = dv.statusCode.name;
            variant = dv.value;
            time = dv.sourceTimestamp ? dv.sourceTimestamp.toISOString() : null;
          } else {
            variant = json.opcuaJsonDecodeVariant(pojo.Value === null ? null : pojo, builder, namespaces);
          }
          decoded.push({ topic, writer: m.DataSetWriterName, kind: m.MessageType, field: name, status, time,
            ...plain(variant) });
        } catch (exc) {
          errors.push(`${m.DataSetWriterName} ${name}: ${exc.message}`);
        }
      }
    }
  }
  console.log(JSON.stringify({ decoded, errors, namespaces }));
}

function plain(variant) {
  if (!variant || variant.value === null || variant.value === undefined) return { type: "Null", value: null };
  const { DataType } = require("node-opcua-client");
  const type = DataType[variant.dataType];
  const v = variant.value;
  if (type === "LocalizedText") return { type, value: { text: v.text, locale: v.locale } };
  if (type === "NodeId" || type === "ExpandedNodeId") return { type, value: v.toString() };
  if (type === "DateTime") return { type, value: v.toISOString() };
  if (type === "ByteString") return { type, value: v.toString("base64") };
  if (typeof v === "bigint" || Array.isArray(v)) return { type, value: JSON.parse(JSON.stringify(v, (k, x) => (typeof x === "bigint" ? x.toString() : x))) };
  return { type, value: v };
}

run().catch((exc) => {
  console.error(exc);
  process.exit(1);
});
