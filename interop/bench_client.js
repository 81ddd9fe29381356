// node-opcua load client for uacell's benchmarks (python -m benchmarks); runs in its own process.
//   node bench_client.js <endpoint> '<json spec>'
// Paths in the spec are browse paths from Objects with namespace keys of lib.js (plus Bench), e.g.
// "/PackML:PackMLObjects/Cell:Filler1". Modes (spec.mode):
//   calls:  spec.sessions sessions (one connection each) call spec.steps in a loop for spec.warmup
//           seconds (default 1, not measured), then for spec.seconds (a step {read: path} reads a value
//           instead); prints calls/s and per-call latency percentiles of the measured period;
//   start:  one session: Reset (wait Idle), Start with spec.parameters PackMLDescriptorDataType
//           (timed), Stop (wait Stopped), again for spec.seconds; prints Start's latency percentiles;
//   notify: one session subscribed (spec.interval ms) to spec.current's value and to the events of
//           spec.object; calls spec.steps in turn and measures from each call's return to the data
//           change and to the event;
//   hold:   opens spec.sessions sessions, each subscribed to spec.current; prints {"ready": n} and keeps
//           them until stdin closes, then prints how many were still alive.
// The last line of stdout is one JSON object.
"use strict";
const {
  OPCUAClient, MessageSecurityMode, SecurityPolicy, AttributeIds, DataType, VariantArrayType, NodeId,
  ClientSubscription, ClientMonitoredItem, TimestampsToReturn, constructEventFilter,
} = require("node-opcua-client");
const { resolve, done, main, NS } = require("./lib");

const BENCH_NS = "urn:uacell:bench";
const now = () => Number(process.hrtime.bigint()) / 1e6; // ms

async function open(endpoint) {
  const client = OPCUAClient.create({
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 3, initialDelay: 200, maxDelay: 2000 },
    securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None,
    requestedSessionTimeout: 120000,
    keepSessionAlive: false,
  });
  await client.connect(endpoint);
  const session = await client.createSession();
  return { client, session };
}

async function namespaces(session) {
  const nsArray = (await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value })).value.value;
  const ns = {};
  for (const [key, uri] of Object.entries({ ...NS, Bench: BENCH_NS })) ns[key] = nsArray.indexOf(uri);
  return ns;
}

async function close({ client, session }) {
  try {
    await session.close();
  } catch (err) {
    /* already gone */
  }
  await client.disconnect();
}

function percentile(sorted, p) {
  if (!sorted.length) return null;
  const i = Math.min(sorted.length - 1, Math.max(0, Math.ceil((p / 100) * sorted.length) - 1));
  return sorted[i];
}

function stats(samples) {
  const sorted = [...samples].sort((a, b) => a - b);
  return { n: sorted.length, p50_ms: percentile(sorted, 50), p99_ms: percentile(sorted, 99) };
}

async function descriptors(session, ns, count) {
  const dataType = new NodeId(NodeId.NodeIdType.NUMERIC, 16, ns.PackML); // PackMLDescriptorDataType
  const eos = [];
  for (let i = 0; i < count; i++) {
    eos.push(await session.constructExtensionObject(dataType, {
      ID: 100 + i,
      name: `Parameter${i}`,
      unit: { namespaceUri: "http://www.opcfoundation.org/UA/units/un/cefact", unitId: 5002584, displayName: { text: "ml" }, description: { text: "millilitre" } },
      value: 10.5 * (i + 1),
    }));
  }
  return { dataType: DataType.ExtensionObject, arrayType: VariantArrayType.Array, value: eos };
}

async function argument(session, ns, arg) {
  if (arg.type === "descriptors") return descriptors(session, ns, arg.count);
  return { dataType: DataType[arg.type], value: arg.value };
}

// Resolved calls: [{objectId, methodId, inputArguments}]
async function prepare(session, ns, steps) {
  const out = [];
  for (const step of steps) {
    if (step.read) {
      out.push({ read: await resolve(session, ns, "i=85", step.read) });
      continue;
    }
    const objectId = await resolve(session, ns, "i=85", step.object);
    const methodId = await resolve(session, ns, objectId, step.method);
    const inputArguments = [];
    for (const arg of step.args || []) inputArguments.push(await argument(session, ns, arg));
    out.push({ objectId, methodId, inputArguments });
  }
  return out;
}

async function call(session, request) {
  if (request.read) {
    const dv = await session.read({ nodeId: request.read, attributeId: AttributeIds.Value });
    if (!dv.statusCode.isGood()) throw new Error(`read ${request.read}: ${dv.statusCode.toString()}`);
    return dv;
  }
  const result = await session.call(request);
  if (!result.statusCode.isGood()) throw new Error(`${request.methodId}: ${result.statusCode.toString()}`);
  const outputs = result.outputArguments || [];
  // Robotics methods answer a status in their first output: 0 is success
  if (outputs.length && typeof outputs[0].value === "number" && outputs[0].dataType === DataType.Int32 && outputs[0].value < 0) {
    throw new Error(`${request.methodId}: result ${outputs[0].value}`);
  }
  return result;
}

async function calls(endpoint, spec) {
  const sessions = await Promise.all(Array.from({ length: spec.sessions }, () => open(endpoint)));
  const ns = await namespaces(sessions[0].session);
  const requests = await prepare(sessions[0].session, ns, spec.steps);
  for (const s of sessions) for (let i = 0; i < 2; i++) for (const r of requests) await call(s.session, r); // every path works
  const latencies = [];
  const perSession = sessions.map(() => 0); // the measured calls of each session (fairness)
  let count = 0;
  let errors = 0;
  let firstError = null;
  // Every session calls in a loop until the deadline; only calls of the measured period are counted.
  const load = (seconds, measured) => {
    const deadline = now() + seconds * 1000;
    return Promise.all(sessions.map(async ({ session }, index) => {
      while (now() < deadline) {
        for (const r of requests) {
          const t = now();
          try {
            await call(session, r);
          } catch (err) {
            errors += 1;
            firstError = firstError || String(err.message || err);
          }
          if (measured) {
            latencies.push(now() - t);
            count += 1;
            perSession[index] += 1;
          }
        }
      }
    }));
  };
  // Warm-up under the same load, not measured: the first second of a run is about half as fast as
  // the rest against every server here, the bare echoes too (docs/performance.md), and a short run
  // would measure mostly that.
  await load(spec.warmup ?? 1, false);
  const t0 = now();
  await load(spec.seconds, true);
  const elapsed = (now() - t0) / 1000;
  await Promise.all(sessions.map(close));
  return {
    calls: count, seconds: elapsed, rate: count / elapsed, errors, first_error: firstError,
    per_session: perSession, ...stats(latencies),
  };
}

async function readText(session, nodeId) {
  const dv = await session.read({ nodeId, attributeId: AttributeIds.Value });
  return dv.statusCode.isGood() && dv.value.value ? dv.value.value.text : dv.statusCode.name;
}

async function waitText(session, nodeId, text, timeoutMs = 10000) {
  const deadline = now() + timeoutMs;
  for (;;) {
    if ((await readText(session, nodeId)) === text) return;
    if (now() > deadline) throw new Error(`waited for ${text} at ${nodeId}`);
    await new Promise((r) => setTimeout(r, 5));
  }
}

async function start(endpoint, spec) {
  const conn = await open(endpoint);
  const { session } = conn;
  const ns = await namespaces(session);
  const unit = await resolve(session, ns, "i=85", spec.object);
  const machine = await resolve(session, ns, unit, "/PackML:BaseStateMachine/PackML:MachineState");
  const execute = await resolve(session, ns, machine, "/PackML:ExecuteState");
  const machineState = await resolve(session, ns, machine, "/CurrentState");
  const executeState = await resolve(session, ns, execute, "/CurrentState");
  const method = async (obj, name) => ({ objectId: obj, methodId: await resolve(session, ns, obj, `/PackML:${name}`), inputArguments: [] });
  const reset = await method(machine, "Reset");
  const stop = await method(machine, "Stop");
  const startCall = await method(execute, "Start");
  startCall.inputArguments = [await descriptors(session, ns, spec.parameters)];
  const latencies = [];
  const deadline = now() + spec.seconds * 1000;
  let round = 0;
  while (now() < deadline || round < 3) {
    if ((await readText(session, machineState)) !== "Execute" || (await readText(session, executeState)) !== "Idle") {
      if ((await readText(session, machineState)) !== "Stopped") {
        await call(session, stop);
        await waitText(session, machineState, "Stopped");
      }
      await call(session, reset);
      await waitText(session, executeState, "Idle");
    }
    const t = now();
    await call(session, startCall);
    if (round > 0) latencies.push(now() - t); // the first is warm-up
    await call(session, stop);
    await waitText(session, machineState, "Stopped");
    round += 1;
  }
  await close(conn);
  return { rounds: round, ...stats(latencies) };
}

async function notify(endpoint, spec) {
  const conn = await open(endpoint);
  const { session } = conn;
  const ns = await namespaces(session);
  const requests = await prepare(session, ns, spec.steps);
  const objectId = await resolve(session, ns, "i=85", spec.object);
  const current = await resolve(session, ns, "i=85", spec.current);
  const sub = ClientSubscription.create(session, {
    requestedPublishingInterval: spec.interval, requestedMaxKeepAliveCount: 100, requestedLifetimeCount: 1000,
    maxNotificationsPerPublish: 0, publishingEnabled: true, priority: 10,
  });
  // node-opcua's ClientSubscription turns a requested 0 into 100 ms; the request leaves on the next turn
  sub.publishingInterval = spec.interval;
  await new Promise((r) => sub.once("started", r));
  let onValue = null;
  let onEvent = null;
  const valueItem = ClientMonitoredItem.create(sub, { nodeId: current, attributeId: AttributeIds.Value },
    { samplingInterval: 0, discardOldest: true, queueSize: 10 }, TimestampsToReturn.Both);
  const eventItem = ClientMonitoredItem.create(sub, { nodeId: objectId, attributeId: AttributeIds.EventNotifier },
    { samplingInterval: 0, discardOldest: true, queueSize: 100, filter: constructEventFilter(["EventType"]) }, TimestampsToReturn.Both);
  valueItem.on("changed", () => { if (onValue) onValue(now()); });
  eventItem.on("changed", () => { if (onEvent) onEvent(now()); });
  await new Promise((r) => setTimeout(r, 500)); // initial values delivered
  const values = [];
  const events = [];
  let missed = 0;
  const deadline = now() + spec.seconds * 1000;
  let round = 0;
  while (now() < deadline || round < 2) {
    for (const r of requests) {
      const gotValue = new Promise((res) => { onValue = res; });
      const gotEvent = new Promise((res) => { onEvent = res; });
      await call(session, r);
      const returned = now();
      const timeout = new Promise((res) => setTimeout(() => res(null), 2000 + spec.interval));
      const [tv, te] = await Promise.all([Promise.race([gotValue, timeout]), Promise.race([gotEvent, timeout])]);
      onValue = onEvent = null;
      if (tv === null || te === null) missed += 1;
      if (round > 0) { // the first round is warm-up
        if (tv !== null) values.push(tv - returned);
        if (te !== null) events.push(te - returned);
      }
    }
    round += 1;
  }
  await sub.terminate();
  await close(conn);
  return { interval: spec.interval, revised_interval: sub.publishingInterval, missed, value: stats(values), event: stats(events) };
}

async function hold(endpoint, spec) {
  const held = [];
  let failed = 0;
  let firstError = null;
  const batch = 10;
  for (let i = 0; i < spec.sessions; i += batch) {
    const opened = await Promise.all(Array.from({ length: Math.min(batch, spec.sessions - i) }, async () => {
      try {
        const conn = await open(endpoint);
        const ns = await namespaces(conn.session);
        const current = await resolve(conn.session, ns, "i=85", spec.current);
        const sub = ClientSubscription.create(conn.session, {
          requestedPublishingInterval: 1000, requestedMaxKeepAliveCount: 10, requestedLifetimeCount: 100,
          maxNotificationsPerPublish: 0, publishingEnabled: true, priority: 1,
        });
        conn.alive = true;
        conn.notifications = 0;
        sub.on("terminated", () => { conn.alive = false; });
        const item = ClientMonitoredItem.create(sub, { nodeId: current, attributeId: AttributeIds.Value },
          { samplingInterval: 250, discardOldest: true, queueSize: 1 }, TimestampsToReturn.Neither);
        item.on("changed", () => { conn.notifications += 1; });
        conn.client.on("connection_lost", () => { conn.alive = false; });
        return conn;
      } catch (err) {
        failed += 1;
        firstError = firstError || String(err.message || err);
        return null;
      }
    }));
    held.push(...opened.filter(Boolean));
  }
  await new Promise((r) => setTimeout(r, 2000)); // every subscription has published its first value
  process.stdout.write(JSON.stringify({ ready: held.length, failed }) + "\n");
  await new Promise((r) => { process.stdin.on("data", r); process.stdin.on("end", r); });
  const alive = held.filter((c) => c.alive && c.notifications > 0).length;
  await Promise.all(held.map((c) => close(c).catch(() => null)));
  return { opened: held.length, failed, alive, first_error: firstError };
}

main(async () => {
  const endpoint = process.argv[2];
  const spec = JSON.parse(process.argv[3]);
  const modes = { calls, start, notify, hold };
  done(await modes[spec.mode](endpoint, spec));
});
