// A Local Discovery Server (node-opcua-server-discovery) for uacell's registration tests.
// Its PKI lives in <pkiDir>: a registering server's certificate lands in <pkiDir>/rejected until the
// test moves it to <pkiDir>/trusted/certs. Multicast DNS is switched off (the tests send nothing
// beyond the loopback interface): the LDS neither announces itself nor the servers registering.
// Usage: node discovery_server.js <port> <pkiDir>; prints "listening" once it serves; stops on SIGTERM.
"use strict";
const path = require("path");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { OPCUABaseServer } = require("node-opcua-server");
const { BonjourHolder } = require("node-opcua-service-discovery"); // node-opcua-server-discovery's own dependency
const { OPCUADiscoveryServer } = require("node-opcua-server-discovery");

BonjourHolder.prototype.announcedOnMulticastSubnet = async function (announcement) {
  this.announcement = announcement;
  return true;
};
BonjourHolder.prototype.stopAnnouncedOnMulticastSubnet = async function () {};
// start() without the mDNS responder and the LDS's own announcement.
OPCUADiscoveryServer.prototype.start = async function () {
  this._preInitTask.push(async () => {
    await this._delayInit();
  });
  await new Promise((resolve, reject) => OPCUABaseServer.prototype.start.call(this, (err) => (err ? reject(err) : resolve())));
};

async function main() {
  const port = Number(process.argv[2]);
  const pkiDir = process.argv[3];
  const serverCertificateManager = new OPCUACertificateManager({
    rootFolder: pkiDir,
    automaticallyAcceptUnknownCertificate: false,
  });
  await serverCertificateManager.initialize();
  const server = new OPCUADiscoveryServer({
    port,
    hostname: "127.0.0.1",
    serverCertificateManager,
    certificateFile: path.join(pkiDir, "own", "certs", "lds.pem"),
    privateKeyFile: path.join(pkiDir, "own", "private", "private_key.pem"),
    serverInfo: { applicationUri: "urn:uacell:test:lds" },
  });
  await server.start();
  process.stdout.write("listening\n");
  process.on("SIGTERM", async () => {
    await server.shutdown();
    process.exit(0);
  });
}

main().catch((err) => {
  console.error(err && err.stack ? err.stack : String(err));
  process.exit(1);
});
