// Decodes Sparkplug B payloads with Eclipse Tahu's own JavaScript library (sparkplug-payload), as a
// host built on Tahu would: reads a JSON array of {"topic", "payload" (base64)} on stdin and prints
// one JSON object {"messages": [{"topic", "seq", "timestamp", "metrics": [...]}]}; Longs as numbers.
"use strict";
const sparkplug = require("sparkplug-payload").get("spBv1.0");

function plain(v) {
  if (v === null || v === undefined) return v;
  if (typeof v === "object" && typeof v.toNumber === "function") return v.toNumber(); // a Long
  if (Array.isArray(v)) return v.map(plain);
  if (typeof v === "object" && !(v instanceof Uint8Array)) {
    const out = {};
    for (const [k, x] of Object.entries(v)) out[k] = plain(x);
    return out;
  }
  return v;
}

let input = "";
process.stdin.on("data", (chunk) => (input += chunk));
process.stdin.on("end", () => {
  const messages = JSON.parse(input).map(({ topic, payload }) => {
    const decoded = sparkplug.decodePayload(Buffer.from(payload, "base64"));
    return { topic, ...plain(decoded) };
  });
  console.log(JSON.stringify({ messages }));
});
