// node-opcua reads the AuditCertificate events of refused X.509 user certificates (OPC 10000-4 6.5.6,
// OPC 10000-5 6.4.13 to 6.4.19; decision 102): an admin session subscribes to the Server object's
// events; then, on a SecurityPolicy None channel, a session tries to log in with each user certificate.
// argv: endpoint adminUser adminPassword then, per certificate, label certDer keyPem
// Prints {refused, events}: per label, the error the login got; the certificate events received (type,
// SourceName, StatusCodeId's name, the Certificate as hex).
"use strict";
const fs = require("fs");
const { UserTokenType } = require("node-opcua-client");
const { done, main, newClient, serverEvents } = require("./lib");

main(async () => {
  const [endpoint, adminUser, adminPassword, ...rest] = process.argv.slice(2);
  const logins = [];
  for (let i = 0; i + 2 < rest.length; i += 3) logins.push({ label: rest[i], cert: rest[i + 1], key: rest[i + 2] });
  const events = [];
  const fields = ["EventType", "SourceName", "StatusCodeId", "Certificate"];
  const { client: admin, session } = await serverEvents(endpoint, adminUser, adminPassword, fields, (values) => {
    if (values[1].value !== "Security/Certificate") return;
    events.push({
      type: values[0].value.toString(),
      sourceName: values[1].value,
      status: values[2].value ? values[2].value.name : null,
      certificate: values[3].value ? Buffer.from(values[3].value).toString("hex") : null,
    });
  });
  await new Promise((res) => setTimeout(res, 300));

  const refused = {};
  const client = newClient();
  await client.connect(endpoint);
  for (const login of logins) {
    try {
      const s = await client.createSession({
        type: UserTokenType.Certificate,
        certificateData: fs.readFileSync(login.cert),
        privateKey: fs.readFileSync(login.key, "ascii"),
      });
      refused[login.label] = null;
      await s.close();
    } catch (err) {
      refused[login.label] = String(err.message || err);
    }
  }
  await client.disconnect();
  const deadline = Date.now() + 10000;
  while (events.length < logins.length && Date.now() < deadline) await new Promise((res) => setTimeout(res, 100));
  await session.close();
  await admin.disconnect();
  await done({ refused, events });
});
