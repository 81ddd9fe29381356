// The audit events of sessions (OPC 10000-4 6.5.6), read by node-opcua: an admin session subscribes to the
// Server object's events; then another session is made anonymously and closed, and a login with a wrong
// password is tried. Prints the audit events of session services it received, in order.
// Usage: node session_audit.js <endpoint> <admin user> <admin password> <other user>
"use strict";
const { UserTokenType } = require("node-opcua-client");
const { done, main, newClient, serverEvents } = require("./lib");

main(async () => {
  const [endpoint, adminUser, adminPassword, otherUser] = process.argv.slice(2);
  const fields = ["EventType", "SourceName", "Status", "ClientUserId", "SessionId", "SecureChannelId", "UserIdentityToken"];
  const events = [];
  const { client: admin, session } = await serverEvents(endpoint, adminUser, adminPassword, fields, (values) => {
    const token = values[6].value;
    events.push({
      type: values[0].value ? values[0].value.toString() : null,
      sourceName: values[1].value,
      status: values[2].value,
      clientUserId: values[3].value === undefined ? null : values[3].value,
      sessionId: values[4].value ? values[4].value.toString() : null,
      channel: values[5].value === undefined ? null : values[5].value,
      token: token ? { kind: token.constructor.name, userName: token.userName || null, password: token.password ? "present" : null } : null,
    });
  });
  await new Promise((res) => setTimeout(res, 300));

  const other = newClient();
  await other.connect(endpoint);
  const otherSession = await other.createSession();
  const otherId = otherSession.sessionId.toString();
  await otherSession.close();
  await other.disconnect();
  const wrong = newClient();
  await wrong.connect(endpoint);
  let refused = null;
  try {
    const s = await wrong.createSession({ type: UserTokenType.UserName, userName: otherUser, password: "not the password" });
    await s.close();
  } catch (err) {
    refused = String(err.message || err);
  }
  await wrong.disconnect();

  const deadline = Date.now() + 10000;
  const closedSeen = () => events.some((e) => e.sourceName === "Session/CloseSession" && e.sessionId === otherId);
  const refusedSeen = () => events.some((e) => e.sourceName === "Session/ActivateSession" && e.status === false);
  while (!(closedSeen() && refusedSeen()) && Date.now() < deadline) await new Promise((res) => setTimeout(res, 100));
  await session.close();
  await admin.disconnect();
  done({ otherId, refused, events });
});
