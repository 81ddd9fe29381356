// HistoryRead from node-opcua: raw values through continuation points, ReadProcessedDetails for five
// aggregates, and node-opcua-aggregates' own Average/Minimum/Maximum/Count on the same raw values;
// then raw values with their bounding values (returnBounds), in one request and two a page; values at
// given instants (ReadAtTimeDetails) with simple and with interpolated bounds; then the events of the
// Server object with an OfType(TransitionEventType) filter.
// argv: endpoint, nodeId, start (ISO), end (ISO), processing interval (ms), bounded start (ISO), bounded end (ISO),
//       instants (ISO, comma-separated)
"use strict";
const {
  AttributeIds, NodeClass, ReadRawModifiedDetails, ReadProcessedDetails, ReadEventDetails, ReadAtTimeDetails, TimestampsToReturn,
  constructEventFilter, ofType, StatusCodes, HistoryReadRequest,
} = require("node-opcua-client");
const { connect, done, main } = require("./lib");

const AGGREGATES = { Average: "i=2342", Minimum: "i=2346", Maximum: "i=2347", Count: "i=2352", TimeAverage: "i=2343", Interpolative: "i=2341" };

function plain(dv) {
  return {
    value: dv.value && dv.value.value !== null && dv.value.value !== undefined ? Number(dv.value.value) : null,
    status: dv.statusCode.value >>> 0,
    time: dv.sourceTimestamp ? dv.sourceTimestamp.toISOString() : null,
    serverTime: dv.serverTimestamp ? dv.serverTimestamp.toISOString() : null,
  };
}

// Every raw value of [startTime, endTime) with bounds, ``perPage`` a request (0: no limit)
async function bounded(session, nodeId, startTime, endTime, perPage) {
  const values = [];
  let continuationPoint = null;
  let pages = 0;
  for (;;) {
    const res = await session.historyRead(new HistoryReadRequest({
      historyReadDetails: new ReadRawModifiedDetails({ startTime, endTime, numValuesPerNode: perPage, isReadModified: false, returnBounds: true }),
      nodesToRead: [{ nodeId, continuationPoint }],
      timestampsToReturn: TimestampsToReturn.Both,
      releaseContinuationPoints: false,
    }));
    const r = res.results[0];
    if (r.statusCode.isNotGood()) throw new Error(`bounded: ${r.statusCode.toString()}`);
    pages += 1;
    values.push(...(r.historyData.dataValues || []).map(plain));
    continuationPoint = r.continuationPoint;
    if (!continuationPoint || continuationPoint.length === 0 || pages > 50) break;
  }
  return { values, pages };
}

function prop(value) {
  return { readValue: () => ({ value: { value } }) };
}

main(async () => {
  const [endpoint, nodeId, startIso, endIso, intervalText, boundStartIso, boundEndIso, instantsText] = process.argv.slice(2);
  const start = new Date(startIso);
  const end = new Date(endIso);
  const interval = Number(intervalText);
  const { client, session } = await connect(endpoint);
  const out = { raw: [], pages: 0, processed: {}, reference: {}, events: [] };

  // raw values, 1000 per request, through continuation points
  let continuationPoint = null;
  for (;;) {
    const res = await session.historyRead(new HistoryReadRequest({
      historyReadDetails: new ReadRawModifiedDetails({ startTime: start, endTime: end, numValuesPerNode: 1000, isReadModified: false }),
      nodesToRead: [{ nodeId, continuationPoint }],
      timestampsToReturn: TimestampsToReturn.Both,
      releaseContinuationPoints: false,
    }));
    const r = res.results[0];
    if (r.statusCode.isNotGood() && r.statusCode.value !== StatusCodes.GoodNoData.value) throw new Error(`raw: ${r.statusCode.toString()}`);
    out.pages += 1;
    out.raw.push(...(r.historyData.dataValues || []));
    continuationPoint = r.continuationPoint;
    if (!continuationPoint || continuationPoint.length === 0) break;
  }

  const shifted = new Date(start.getTime() + 100);
  for (const [name, id, from] of [...Object.entries(AGGREGATES), ["InterpolativeShifted", AGGREGATES.Interpolative, shifted]]) {
    const res = await session.historyRead(new HistoryReadRequest({
      historyReadDetails: new ReadProcessedDetails({ startTime: from || start, endTime: end, processingInterval: interval, aggregateType: [id] }),
      nodesToRead: [{ nodeId }],
      timestampsToReturn: TimestampsToReturn.Source,
      releaseContinuationPoints: false,
    }));
    const r = res.results[0];
    out.processed[name] = { status: r.statusCode.name, values: (r.historyData.dataValues || []).map(plain) };
  }

  // node-opcua-aggregates on the raw values uacell returned: the same configuration as uacell's
  // HA Configuration (Stepped, TreatUncertainAsBad, 100 % data good/bad)
  const agg = await import("node-opcua-aggregates");
  const raw = out.raw;
  const fake = {
    nodeClass: NodeClass.Variable,
    historyRead: (_ctx, _details, _range, _encoding, _cp, callback) => callback(null, { historyData: { dataValues: raw } }),
    $historicalDataConfiguration: {
      stepped: prop(true),
      aggregateConfiguration: {
        percentDataBad: prop(100), percentDataGood: prop(100), treatUncertainAsBad: prop(true), useSlopedExtrapolation: prop(false),
      },
    },
  };
  const run = (fn, from = start) => new Promise((resolve, reject) => fn(fake, interval, from, end, (err, dvs) => (err ? reject(err) : resolve(dvs.map(plain)))));
  out.reference.Average = await run(agg.getAverageData);
  out.reference.Minimum = await run(agg.getMinData);
  out.reference.Maximum = await run(agg.getMaxData);
  out.reference.Count = await run(agg.getCountData);
  out.reference.InterpolativeShifted = await run(agg.getInterpolatedData, shifted);
  out.raw = raw.map(plain);

  out.bounded = await bounded(session, nodeId, new Date(boundStartIso), new Date(boundEndIso), 0);
  out.boundedPaged = await bounded(session, nodeId, new Date(boundStartIso), new Date(boundEndIso), 2);

  out.atTime = {};
  for (const useSimpleBounds of [true, false]) {
    const res = await session.historyRead(new HistoryReadRequest({
      historyReadDetails: new ReadAtTimeDetails({ reqTimes: instantsText.split(",").map((t) => new Date(t)), useSimpleBounds }),
      nodesToRead: [{ nodeId }],
      timestampsToReturn: TimestampsToReturn.Both,
      releaseContinuationPoints: false,
    }));
    const r = res.results[0];
    out.atTime[useSimpleBounds ? "simple" : "interpolated"] = { status: r.statusCode.name, values: (r.historyData.dataValues || []).map(plain) };
  }

  const filter = constructEventFilter(["EventType", "SourceName", "Message", "ToState"], ofType("TransitionEventType"));
  const ev = await session.historyRead(new HistoryReadRequest({
    historyReadDetails: new ReadEventDetails({ startTime: new Date(Date.now() - 3600000), endTime: new Date(Date.now() + 3600000), numValuesPerNode: 0, filter }),
    nodesToRead: [{ nodeId: "i=2253" }],
    timestampsToReturn: TimestampsToReturn.Both,
    releaseContinuationPoints: false,
  }));
  const er = ev.results[0];
  out.eventStatus = er.statusCode.name;
  out.events = (er.historyData.events || []).map((e) => ({
    type: e.eventFields[0].value ? e.eventFields[0].value.toString() : null,
    source: e.eventFields[1].value,
    toState: e.eventFields[3].value ? e.eventFields[3].value.text : null,
  }));
  await session.close();
  await client.disconnect();
  await done(out);
});
