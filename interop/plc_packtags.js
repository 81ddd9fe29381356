// A PLC for uacell's gateway: node-opcua's server holding ISA-TR88 PackTags for one or more units,
// and a scan-cycle program running each unit's TR88 state machine (the PLC owns the state).
//
//   node interop/plc_packtags.js PORT [UNIT,UNIT,...] [ACTING_MS]
//
// Tags, per unit U (namespace urn:uacell:plc, string NodeIds "U.PackTags.<path>"):
//   Command.CntrlCmd (Int32), Command.CmdChangeRequest (Boolean), Command.UnitMode (Int32),
//   Command.UnitModeChangeRequest (Boolean), Command.MachSpeed (Float), Command.Parameter[i].Value (Float, 5),
//   Status.StateCurrent (Int32, TR88 numbers), Status.UnitModeCurrent (Int32), Status.CurMachSpeed (Float),
//   Status.MachSpeed (Float), Admin.ProdProcessedCount (Int32), Admin.ProdDefectiveCount (Int32),
//   Admin.StopReason.ID (Int32), Admin.Alarm[i].ID (Int32, 4; written by tests: the PLC's active alarms);
//   and for tests: Sim.Refuse (Boolean: requests are taken and ignored), Sim.Frozen (Boolean: no scan),
//   Sim.Fault (Boolean: a rising edge aborts the unit with StopReason 42), Sim.Parameters (Float[]: the
//   Command.Parameter values the last Start took). Each tag is also a node of a tree, for browse paths:
//   Objects/U/PackTags/Command/CntrlCmd (NodeId "U.Tree.Command.CntrlCmd").
// The program, every 5 ms: take a change request (clear it; act on it when TR88 allows the command in the
// state), end an acting state after ACTING_MS, produce in Execute at MachSpeed packages/min.
// Prints "listening" once clients can connect; stops on SIGTERM.
// A locked-down PLC, for the gateway's security tests: PLC_PKI=<dir> offers Basic256Sha256 Sign and
// SignAndEncrypt only (client certificates accepted and trusted on first contact, the PKI in <dir>);
// PLC_USER=<name>:<password> admits that user only (no anonymous sessions).
"use strict";
const path = require("path");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");
const { OPCUAServer, Subscription, MonitoredItem } = require("node-opcua-server");

// Publish as fast as a client asks, down to 10 ms, as a PLC's OPC UA server does (node-opcua's own
// floor is 50 ms); the tags are exception-based (MinimumSamplingInterval 0: see leaf() below).
Subscription.minimumPublishingInterval = 10;
MonitoredItem.minimumSamplingInterval = 10;
const { DataType, Variant, SecurityPolicy, MessageSecurityMode } = require("node-opcua-client");

const S = {
  Clearing: 1, Stopped: 2, Starting: 3, Idle: 4, Suspended: 5, Execute: 6, Stopping: 7, Aborting: 8,
  Aborted: 9, Holding: 10, Held: 11, Unholding: 12, Suspending: 13, Unsuspending: 14, Resetting: 15,
  Completing: 16, Complete: 17,
};
const ACTING_NEXT = {
  [S.Clearing]: S.Stopped, [S.Starting]: S.Execute, [S.Stopping]: S.Stopped, [S.Aborting]: S.Aborted,
  [S.Holding]: S.Held, [S.Unholding]: S.Execute, [S.Suspending]: S.Suspended, [S.Unsuspending]: S.Execute,
  [S.Resetting]: S.Idle, [S.Completing]: S.Complete,
};
const STOPPABLE = [S.Idle, S.Starting, S.Execute, S.Holding, S.Held, S.Unholding, S.Suspending, S.Suspended,
  S.Unsuspending, S.Completing, S.Complete, S.Resetting];
// CntrlCmd -> (from states -> to state)
const COMMANDS = {
  1: [[S.Stopped, S.Complete], S.Resetting],
  2: [[S.Idle], S.Starting],
  3: [STOPPABLE, S.Stopping],
  4: [[S.Execute], S.Holding],
  5: [[S.Held], S.Unholding],
  6: [[S.Execute], S.Suspending],
  7: [[S.Suspended], S.Unsuspending],
  8: [Object.values(S).filter((s) => s !== S.Aborting && s !== S.Aborted), S.Aborting],
  9: [[S.Aborted], S.Clearing],
  10: [[S.Execute], S.Completing],
};
const PARAMETERS = 5;
const ALARMS = 4;

function tagsOf() {
  const t = {
    "Command.CntrlCmd": [DataType.Int32, 0], "Command.CmdChangeRequest": [DataType.Boolean, false],
    "Command.UnitMode": [DataType.Int32, 1], "Command.UnitModeChangeRequest": [DataType.Boolean, false],
    "Command.MachSpeed": [DataType.Float, 60.0],
    "Status.StateCurrent": [DataType.Int32, S.Stopped], "Status.UnitModeCurrent": [DataType.Int32, 1],
    "Status.CurMachSpeed": [DataType.Float, 0.0], "Status.MachSpeed": [DataType.Float, 60.0],
    "Admin.ProdProcessedCount": [DataType.Int32, 0], "Admin.ProdDefectiveCount": [DataType.Int32, 0],
    "Admin.StopReason.ID": [DataType.Int32, 0],
    "Sim.Refuse": [DataType.Boolean, false], "Sim.Frozen": [DataType.Boolean, false],
    "Sim.Fault": [DataType.Boolean, false],
  };
  for (let i = 0; i < PARAMETERS; i++) t[`Command.Parameter[${i}].Value`] = [DataType.Float, 0.0];
  for (let i = 0; i < ALARMS; i++) t[`Admin.Alarm[${i}].ID`] = [DataType.Int32, 0];
  return t;
}

class Unit {
  constructor(name, actingMs) {
    this.name = name;
    this.actingMs = actingMs;
    this.v = {};
    this.types = {};
    for (const [k, [type, value]] of Object.entries(tagsOf())) {
      this.v[k] = value;
      this.types[k] = type;
    }
    this.v["Sim.Parameters"] = [];
    this.nodes = {}; // tag -> its variables (flat and in the tree)
    this.published = {}; // tag -> the value its variables hold
    this.enteredAt = Date.now();
    this.produced = 0;
    this.lastFault = false;
  }
  enter(state) {
    this.v["Status.StateCurrent"] = state;
    this.enteredAt = Date.now();
  }
  scan(now) {
    const v = this.v;
    if (v["Sim.Frozen"]) return;
    const state = v["Status.StateCurrent"];
    if (v["Sim.Fault"] && !this.lastFault && COMMANDS[8][0].includes(state)) {
      v["Admin.StopReason.ID"] = 42;
      this.enter(S.Aborting);
    }
    this.lastFault = v["Sim.Fault"];
    if (v["Command.CmdChangeRequest"]) {
      v["Command.CmdChangeRequest"] = false;
      const rule = COMMANDS[v["Command.CntrlCmd"]];
      if (!v["Sim.Refuse"] && rule && rule[0].includes(v["Status.StateCurrent"])) {
        if (v["Command.CntrlCmd"] === 2) {
          this.v["Sim.Parameters"] = [...Array(PARAMETERS).keys()].map((i) => v[`Command.Parameter[${i}].Value`]);
        }
        this.enter(rule[1]);
      }
    }
    if (v["Command.UnitModeChangeRequest"]) {
      v["Command.UnitModeChangeRequest"] = false;
      const s = v["Status.StateCurrent"];
      if (!v["Sim.Refuse"] && [S.Stopped, S.Idle, S.Aborted].includes(s)) v["Status.UnitModeCurrent"] = v["Command.UnitMode"];
    }
    if (v["Command.MachSpeed"] > 0) v["Status.MachSpeed"] = v["Command.MachSpeed"];
    const current = v["Status.StateCurrent"];
    if (ACTING_NEXT[current] !== undefined && now - this.enteredAt >= this.actingMs) this.enter(ACTING_NEXT[current]);
    if (v["Status.StateCurrent"] === S.Execute) {
      v["Status.CurMachSpeed"] = v["Status.MachSpeed"];
      this.produced += (v["Status.MachSpeed"] / 60000) * (now - (this.lastScan || now));
      const whole = Math.floor(this.produced);
      if (whole > 0) {
        this.produced -= whole;
        v["Admin.ProdProcessedCount"] += whole;
      }
    } else {
      v["Status.CurMachSpeed"] = 0.0;
    }
    this.lastScan = now;
    this.publish();
  }
  publish() {
    for (const [key, variables] of Object.entries(this.nodes)) {
      const value = this.v[key];
      if (this.published[key] === value) continue;
      this.published[key] = value;
      const array = key === "Sim.Parameters";
      const dataType = array ? DataType.Float : this.types[key];
      for (const variable of variables) {
        variable.setValueFromSource(new Variant({ dataType, arrayType: array ? 1 : undefined, value }));
      }
    }
  }
}

async function main() {
  const port = Number(process.argv[2]);
  const names = (process.argv[3] || "Capper").split(",").filter((n) => n);
  const actingMs = Number(process.argv[4] || 100);
  const options = { port, hostname: "127.0.0.1", serverInfo: { applicationUri: "urn:uacell:plc" } };
  if (process.env.PLC_PKI) {
    const pki = process.env.PLC_PKI;
    options.serverCertificateManager = new OPCUACertificateManager({ rootFolder: pki, automaticallyAcceptUnknownCertificate: true });
    await options.serverCertificateManager.initialize();
    options.certificateFile = path.join(pki, "own", "certs", "plc.pem");
    options.privateKeyFile = path.join(pki, "own", "private", "private_key.pem");
    options.securityPolicies = [SecurityPolicy.Basic256Sha256];
    options.securityModes = [MessageSecurityMode.Sign, MessageSecurityMode.SignAndEncrypt];
  }
  if (process.env.PLC_USER) {
    const [user, password] = process.env.PLC_USER.split(":");
    options.allowAnonymous = false;
    options.userManager = { isValidUser: (u, p) => u === user && p === password };
  }
  const server = new OPCUAServer(options);
  await server.initialize();
  const space = server.engine.addressSpace;
  const ns = space.registerNamespace("urn:uacell:plc");
  const units = names.map((n) => new Unit(n, actingMs));
  for (const unit of units) {
    const folder = ns.addObject({ browseName: unit.name, nodeId: `s=${unit.name}`, organizedBy: space.rootFolder.objects });
    const keys = [...Object.keys(unit.types), "Sim.Parameters"];
    // The same tags once more as a tree, for clients that address them by browse path:
    // Objects/<unit>/PackTags/Command/CntrlCmd, .../Command/Parameter[0]/Value (NodeIds "<unit>.Tree.<path>").
    const tree = ns.addObject({ browseName: "PackTags", nodeId: `s=${unit.name}.Tree`, componentOf: folder });
    const branches = { "": tree };
    const branch = (path) => {
      if (!(path in branches)) {
        const cut = path.lastIndexOf(".");
        const parent = branch(cut < 0 ? "" : path.slice(0, cut));
        branches[path] = ns.addObject({ browseName: path.slice(cut + 1), nodeId: `s=${unit.name}.Tree.${path}`, componentOf: parent });
      }
      return branches[path];
    };
    for (const key of keys) {
      const array = key === "Sim.Parameters";
      const cut = key.lastIndexOf(".");
      // The program's values are the truth (unit.v): a client's write lands there at once, and the
      // end of each scan publishes what changed (setValueFromSource), so subscriptions are served
      // exception-based (MinimumSamplingInterval 0): a change goes out with the next publish, as
      // from a PLC whose OPC UA server is told of changes rather than sampling its tags.
      const leaf = (parent, browseName, nodeId) => {
        const dataType = array ? DataType.Float : unit.types[key];
        const variable = ns.addVariable({
          componentOf: parent,
          browseName,
          nodeId,
          dataType,
          valueRank: array ? 1 : -1,
          accessLevel: array ? "CurrentRead" : "CurrentRead | CurrentWrite",
          userAccessLevel: array ? "CurrentRead" : "CurrentRead | CurrentWrite",
          minimumSamplingInterval: 0,
          value: new Variant({ dataType, arrayType: array ? 1 : undefined, value: unit.v[key] }),
        });
        variable.on("value_changed", (dv) => {
          if (!array && dv.value.value !== unit.v[key]) {
            unit.v[key] = dv.value.value;
            unit.published[key] = dv.value.value;
            for (const other of unit.nodes[key]) if (other !== variable) other.setValueFromSource(dv.value);
          }
        });
        (unit.nodes[key] = unit.nodes[key] || []).push(variable);
      };
      leaf(folder, `PackTags.${key}`, `s=${unit.name}.PackTags.${key}`);
      leaf(branch(key.slice(0, cut)), key.slice(cut + 1), `s=${unit.name}.Tree.${key}`);
    }
  }
  setInterval(() => {
    const now = Date.now();
    for (const unit of units) unit.scan(now);
  }, 5);
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
