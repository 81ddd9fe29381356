// A bare node-opcua server for uacell's benchmarks: one echo method Objects/Bench/Echo (Variant in, same out),
// optionally loading NodeSet files given after the port (e.g. DI, IA, Robotics, PackML).
// Prints "listening" once clients can connect; stops on SIGTERM.
"use strict";
const { OPCUAServer } = require("node-opcua-server");
const { DataType, StatusCodes, Variant } = require("node-opcua-client");
const { nodesets } = require("node-opcua-nodesets"); // node-opcua-server's own dependency

async function main() {
  const port = Number(process.argv[2]);
  const files = process.argv.slice(3);
  const server = new OPCUAServer({
    port,
    hostname: "127.0.0.1",
    nodeset_filename: [nodesets.standard, ...files],
    serverInfo: { applicationUri: "urn:uacell:bench:node-opcua" },
    maxConnectionsPerEndpoint: 2000,
    serverCapabilities: { maxSessions: 2000 },
  });
  await server.initialize();
  const ns = server.engine.addressSpace.registerNamespace("urn:uacell:bench");
  const bench = ns.addObject({ browseName: "Bench", nodeId: "s=Bench", organizedBy: server.engine.addressSpace.rootFolder.objects });
  const method = ns.addMethod(bench, {
    browseName: "Echo",
    nodeId: "s=Echo",
    inputArguments: [{ name: "value", dataType: DataType.Variant, valueRank: -1 }],
    outputArguments: [{ name: "value", dataType: DataType.Variant, valueRank: -1 }],
  });
  method.bindMethod((inputArguments, context, callback) => {
    callback(null, { statusCode: StatusCodes.Good, outputArguments: inputArguments.map((v) => new Variant(v)) });
  });
  await server.start();
  process.stdout.write("listening\n");
  process.on("SIGTERM", async () => {
    await server.shutdown(0);
    process.exit(0);
  });
}

main().catch((err) => {
  console.error(err && err.stack ? err.stack : String(err));
  process.exit(1);
});
