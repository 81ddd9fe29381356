// Event items whose WhereClause is node-opcua's ofType (OPC 10000-4 7.7.3: an event of the type or of a
// subtype): one on the Server object for BaseEventType, one for ConditionType. Filler1 is reset, which
// fires TransitionEvents (TransitionEventType, a subtype of BaseEventType and not of ConditionType).
// Prints the event types each item was sent. Then an item whose WhereClause uses BitwiseAnd, which the
// server does not evaluate, and one selecting an attribute that does not exist: the item's status and
// the EventFilterResult (OPC 10000-4 7.22.3) of each.
"use strict";
const {
  AttributeIds, ClientSubscription, ClientMonitoredItem, TimestampsToReturn, constructEventFilter, ofType,
  EventFilter, LiteralOperand, FilterOperator, ContentFilterElement, SimpleAttributeOperand, MonitoringMode, DataType,
} = require("node-opcua-client");
const { connect, resolve, done, main, FILLER } = require("./lib");

main(async () => {
  const endpoint = process.argv[2];
  const { client, session, ns } = await connect(endpoint);
  const subscription = ClientSubscription.create(session, {
    requestedPublishingInterval: 50, requestedLifetimeCount: 1000, requestedMaxKeepAliveCount: 20,
    maxNotificationsPerPublish: 100, publishingEnabled: true, priority: 1,
  });
  const out = { BaseEventType: [], ConditionType: [] };
  let wake = () => {};
  const made = [];
  for (const type of Object.keys(out)) {
    const item = ClientMonitoredItem.create(
      subscription,
      { nodeId: "i=2253", attributeId: AttributeIds.EventNotifier },
      { samplingInterval: 0, discardOldest: true, queueSize: 100, filter: constructEventFilter(["EventType"], ofType(type)) },
      TimestampsToReturn.Neither,
    );
    made.push(new Promise((r) => item.once("initialized", r)));
    item.on("changed", (values) => {
      out[type].push(values[0].value ? values[0].value.toString() : null);
      wake();
    });
  }
  await Promise.all(made); // the items exist before the events
  const machine = await resolve(session, ns, await resolve(session, ns, "i=85", FILLER), "/PackML:BaseStateMachine/PackML:MachineState");
  const reset = await session.call({ objectId: machine, methodId: await resolve(session, ns, machine, "/PackML:Reset"), inputArguments: [] });
  out.reset = reset.statusCode.name;
  const deadline = Date.now() + 20000;
  while (!out.BaseEventType.includes("ns=0;i=2311") && Date.now() < deadline) {
    await new Promise((r) => { wake = r; setTimeout(r, 200); });
  }
  const fields = constructEventFilter(["EventType"]).selectClauses;
  const filters = {
    bitwise: new EventFilter({
      selectClauses: fields,
      whereClause: { elements: [new ContentFilterElement({
        filterOperator: FilterOperator.BitwiseAnd,
        filterOperands: [fields[0], new LiteralOperand({ value: { dataType: DataType.UInt32, value: 1 } })],
      })] },
    }),
    badSelect: new EventFilter({
      selectClauses: [...fields, new SimpleAttributeOperand({ typeDefinitionId: "i=2041", browsePath: [], attributeId: 99 })],
    }),
  };
  const answered = await session.createMonitoredItems({
    subscriptionId: subscription.subscriptionId,
    timestampsToReturn: TimestampsToReturn.Neither,
    itemsToCreate: Object.values(filters).map((filter, i) => ({
      itemToMonitor: { nodeId: "i=2253", attributeId: AttributeIds.EventNotifier },
      monitoringMode: MonitoringMode.Reporting,
      requestedParameters: { clientHandle: 990 + i, samplingInterval: 0, queueSize: 10, discardOldest: true, filter },
    })),
  });
  out.filterResults = Object.keys(filters).map((name, i) => {
    const result = answered.results[i];
    const fr = result.filterResult || {};
    const where = fr.whereClauseResult ? fr.whereClauseResult.elementResults || [] : [];
    return {
      name,
      status: result.statusCode.name,
      selects: (fr.selectClauseResults || []).map((c) => c.name),
      elements: where.map((e) => e.statusCode.name),
    };
  });
  await subscription.terminate();
  await session.close();
  await client.disconnect();
  await done(out);
});
