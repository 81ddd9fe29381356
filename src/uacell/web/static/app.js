// uacell web HMI: renders whatever cell the server describes, live from server-sent events.
// Holds no rules: a button is enabled exactly when the server says the method is Executable and
// UserExecutable for this user (and no other session holds a lock over it); every call goes to
// the server in this user's own OPC UA session and its answer is shown as it came.
"use strict";

const S = {
  csrf: "", user: null, layout: null, values: {}, methods: {}, events: [], files: {}, modules: {},
  status: "connecting", problem: "", es: null, myLocks: new Set(),
};

const $ = (sel, root = document) => root.querySelector(sel);
const $$ = (sel, root = document) => Array.from(root.querySelectorAll(sel));
const SVGNS = "http://www.w3.org/2000/svg";

function el(tag, attrs = {}, ...children) {
  const e = tag.startsWith("svg:") ? document.createElementNS(SVGNS, tag.slice(4)) : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "text") e.textContent = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c);
  return e;
}

// --- talking to the HMI server -----------------------------------------------------------------

async function api(path, body) {
  const res = await fetch(path, {
    method: "POST", credentials: "same-origin",
    headers: {"Content-Type": "application/json", "X-CSRF-Token": token()},
    body: JSON.stringify(body || {}),
  });
  let data = {};
  try { data = await res.json(); } catch (e) { data = {error: `HTTP ${res.status}`}; }
  if (res.status === 401 && data.expired) { sessionExpired(); throw new Error("session expired"); }
  return {status: res.status, data};
}

// The web session's token: sent with every request beside the cookie. It is kept in this origin's
// storage (scheme, host and port), which no other port of the host can read, while the cookie goes
// to every port of the host (docs/web.md, "What the browser gets").
const TOKEN_KEY = "uacell-token";
function keepToken(token) {
  S.csrf = token;
  try { localStorage.setItem(TOKEN_KEY, token); } catch (e) { /* storage off: this tab keeps it */ }
}
function storedToken() {
  try { return localStorage.getItem(TOKEN_KEY) || ""; } catch (e) { return ""; }
}
// The stored one first: the cookie is shared by every tab of this origin, and so is the token (a
// login in another tab renewed both).
const token = () => storedToken() || S.csrf;

async function loadSession() {
  const res = await fetch("/api/session", {credentials: "same-origin", headers: {"X-CSRF-Token": token()}});
  const data = await res.json();
  keepToken(data.csrf);
  return data;
}

function sessionExpired(reason) {
  if (S.es) { S.es.close(); S.es = null; }
  const wasUser = S.user;
  S.user = null;
  showUser();
  loadSession().then(() => {
    openLogin(reason ? `${reason}.` : wasUser ? `Your session has expired. Log in again, ${wasUser}.` : "Your session has expired.");
    connect();
  });
}

function connect() {
  if (S.es) S.es.close();
  const es = new EventSource(`/api/events?key=${encodeURIComponent(token())}`);
  S.es = es;
  es.onmessage = (m) => handle(JSON.parse(m.data));
  es.onopen = () => { if (S.status === "web-lost") setConn("connecting", ""); };
  es.onerror = () => {
    if (es !== S.es) return;
    if (es.readyState === EventSource.CLOSED) {
      // The HMI refused the stream: the web session ended (or the HMI restarted).
      loadSession().then((d) => {
        if (d.fresh && S.user) sessionExpired(); else setTimeout(connect, 1000);
      }).catch(() => { setConn("web-lost", "The HMI cannot be reached; retrying…"); setTimeout(connect, 2000); });
    } else {
      setConn("web-lost", "The HMI cannot be reached; retrying…");
    }
  };
}

function handle(m) {
  switch (m.type) {
    case "snapshot":
      S.layout = m.layout; S.values = m.values; S.methods = m.methods; S.events = m.events;
      S.files = m.files; S.modules = m.modules; S.user = m.user; S.role = m.role;
      document.body.dataset.session = m.user || "anonymous";  // whose session the page now shows
      setConn(m.status, m.problem);
      showUser();
      render();
      break;
    case "values":
      Object.assign(S.values, m.values);
      update();
      break;
    case "methods":
      Object.assign(S.methods, m.methods);
      updateButtons();
      break;
    case "event":
      S.events.unshift(m.event);
      S.events.length = Math.min(S.events.length, 30);
      renderEvents();
      break;
    case "events": S.events = m.events; renderEvents(); break;
    case "files": S.files = m.files; renderFiles(); break;
    case "modules": S.modules = m.modules; update(); break;
    case "status": setConn(m.status, m.problem); break;
    case "expired": sessionExpired(m.reason); break;
  }
}

function setConn(status, problem) {
  S.status = status; S.problem = problem || "";
  const b = $("#conn");
  b.dataset.status = status;
  b.textContent = {connected: "live", unreachable: "server unreachable", "web-lost": "HMI unreachable",
                   connecting: "connecting…", "login-required": "log in", busy: "HMI busy",
                   released: "connecting…"}[status] || status;
  const n = $("#notice");
  if (status === "connected") { n.hidden = true; n.textContent = ""; }
  else if (status === "login-required") { n.hidden = false; n.textContent = `${problem}.`; openLogin(`${problem}.`); }
  else if (status === "busy") { n.hidden = false; n.textContent = `${problem}.`; }
  else if (problem) { n.hidden = false; n.textContent = `${problem}. Reconnecting…`; }
  updateButtons();
}

function showUser() {
  $("#who").textContent = S.user ? S.user : "anonymous";
  $("#role").textContent = S.role || "";  // as the server says (its Server/CurrentRole)
  $("#role").hidden = !S.role;
  $("#login-open").hidden = !!S.user;
  $("#logout").hidden = !S.user;
}

// --- calls -------------------------------------------------------------------------------------

// Refusals in plain words; the status code's name stays beside them for whoever looks it up.
const PLAIN = {
  BadUserAccessDenied: "your role may not do this (log in as a user who may)",
  BadInvalidState: "not possible in the current state",
  BadInvalidArgument: "a value is outside what the machine accepts",
  BadOutOfRange: "a value is outside what the machine accepts",
  BadTypeMismatch: "a value has the wrong type",
  BadArgumentsMissing: "a value is missing",
  BadLocked: "someone else holds the lock",
  BadResourceUnavailable: "another client holds the lock or the resource is busy",
  BadNodeIdUnknown: "no such program or node",
  BadNotFound: "not found",
  BadTooManySessions: "the HMI or the server serves too many users right now",
  BadServerNotConnected: "the server is not connected",
  BadCommunicationError: "the server cannot be reached",
  BadTimeout: "the machine did not answer in time",
  BadIdentityTokenRejected: "wrong user name or password",
  BadMethodInvalid: "this server does not offer it",
};
// What a non-zero Status of an operation method means, in words: filled by the views (registerView).
const STATUS_PLAIN = {};

function clock() {
  return new Date().toLocaleTimeString([], {hour: "2-digit", minute: "2-digit", second: "2-digit"});
}

function showResult(what, r, explain) {
  const box = $("#result");
  box.hidden = false;
  box.className = r.good ? "good" : "bad";
  box.dataset.code = r.code || "";
  let text = `${what}: `;
  if (r.good) text += "done";
  let specific = "";
  if (!r.good) {
    specific = explain && ["BadInvalidArgument", "BadOutOfRange"].includes(r.code) ? explain() : "";
    text += `${specific || PLAIN[r.code] || r.meaning || "refused"} (${r.code})`;
  }
  if (r.good && r.code && r.code !== "Good") text += ` (${r.code})`;
  if (r.status_name !== undefined && r.outputs && r.outputs.length) {
    const plain = r.outputs[0] !== 0 ? STATUS_PLAIN[r.status_name] : "";
    text += `, Status ${r.outputs[0]}${r.status_name ? " " + r.status_name : ""}${plain ? `: ${plain}` : ""}`;
  } else if (r.good && r.outputs && r.outputs.length) {
    text += ` → ${JSON.stringify(r.outputs)}`;
  }
  if (r.argument_results && !specific) text += ` [arguments: ${r.argument_results.join(", ")}]`;
  box.textContent = "";
  box.append(el("time", {class: "r-time", text: clock()}), " ", el("span", {class: "r-text", text}));
}

async function call(key, args, label, explain) {
  try {
    const {status, data} = await api("/api/call", {key, args: args || []});
    if (status !== 200) showResult(label || key, {good: false, code: data.error || `HTTP ${status}`});
    else showResult(label || key, data, explain);
    return data;
  } catch (e) {
    if (e.message !== "session expired") showResult(label || key, {good: false, code: "BadCommunicationError", meaning: String(e)});
    return null;
  }
}

function methodUsable(key) {
  const m = S.methods[key];
  return !!(m && m.executable && m.user_executable);
}

// A lock held by another session over this key's element (the element or any element above it).
function lockHolder(lockScopes) {
  for (const lock of lockScopes || []) {
    if (!lock) continue;
    const v = lock.variables;
    if (S.values[v.Locked] && !S.myLocks.has(v.Locked)) {
      return S.values[v.LockingUser] || S.values[v.LockingClient] || "another client";
    }
  }
  return null;
}

function button(label, key, opts = {}) {
  const b = el("button", {type: "button", "data-method": key || "", "data-label": label, class: opts.cls || null,
                          title: key || "not offered by this server"}, label);
  b._locks = opts.locks || [];
  b._keys = opts.keys || (key ? [key] : []);
  b._why = opts.why || null;
  b.addEventListener("click", async () => {
    const k = b._keys.find(methodUsable) || b._keys[0];
    if (!k) return;
    if (opts.confirm && !window.confirm(opts.confirm)) return;
    const args = opts.args ? opts.args() : [];
    if (args === null) return;
    const r = await call(k, args, label, opts.explain);
    if (r && opts.after) opts.after(r);
  });
  return b;
}

// Why a command cannot be used now, in words; "" when it can.
function whyDisabled(b, live, holder) {
  if (!b._keys.length) return "this server does not offer it";
  if (!live) return "the server is not connected";
  if (holder) return `locked by ${holder}`;
  if (b._keys.some(methodUsable)) return "";
  const known = b._keys.map((k) => [k, S.methods[k]]).filter(([, m]) => m);
  if (known.some(([, m]) => m.executable && !m.user_executable)) {
    return S.user ? `your role may not do this (${S.user})` : "your role may not do this: log in";
  }
  if (S.alarmActive && b.closest(".controller")) return "an alarm is active (see the banner)";
  const special = b._why ? b._why() : "";
  if (special && !S.alarmActive) return special;
  const state = b._state ? b._state()
    : known.map(([k]) => S.values[`${k.split("/").slice(0, -1).join("/")}/CurrentState`]).find(Boolean);
  return state ? `not possible in state ${state}` : "not possible now";
}

function updateButtons() {
  const live = S.status === "connected";
  for (const b of $$("button[data-method]")) {
    if (!b._keys) continue;
    const holder = lockHolder(b._locks);
    const why = whyDisabled(b, live, holder);
    b.disabled = !!why;
    b.classList.toggle("locked", !!holder);
    b.title = why ? `${b.dataset.label}: ${why}` : b.dataset.label;
    b.dataset.why = why;
  }
  // Under each row of commands, in the page: why those that cannot be used now cannot.
  for (const row of $$(".commands")) {
    let line = row.nextElementSibling;
    if (!line || !line.classList.contains("why-line")) {
      line = el("p", {class: "why-line", "aria-live": "polite"});
      row.after(line);
    }
    const reasons = $$("button[data-method]", row).filter((b) => b.dataset.why)
      .map((b) => `${b.dataset.label}: ${b.dataset.why}`);
    line.textContent = reasons.length ? `Not available now — ${reasons.join("; ")}` : "";
  }
  for (const span of $$("[data-lock-note]")) {
    const holder = lockHolder(span._locks);
    span.textContent = holder ? `locked by ${holder}` : "";
    span.hidden = !holder;
  }
}

// --- rendering ---------------------------------------------------------------------------------

// What the user is in the middle of (open sections, typed text) survives a re-render (a new
// snapshot after a reconnect or a login): keyed by the nearest card's id and the element's class.
function uiKey(node) {
  const owner = node.parentElement ? node.parentElement.closest("[id]") : null;
  return `${owner ? owner.id : ""}|${node.tagName}|${node.className}`;
}

function saveUi(root) {
  const saved = new Map(), seen = new Map();
  const fields = $$("input, textarea, select", root).filter((n) => !n.closest(".param-rows"));
  for (const n of fields) seen.set(uiKey(n), (seen.get(uiKey(n)) || 0) + 1);
  for (const n of $$("details", root)) saved.set(uiKey(n), n.open);
  for (const n of fields) if (seen.get(uiKey(n)) === 1 && n.value) saved.set(`${uiKey(n)}|value`, n.value);
  return saved;
}

function restoreUi(root, saved) {
  for (const n of $$("details", root)) if (saved.has(uiKey(n))) n.open = saved.get(uiKey(n));
  for (const n of $$("input, textarea, select", root)) {
    const value = saved.get(`${uiKey(n)}|value`);
    if (value !== undefined && !n.closest(".param-rows")) n.value = value;
  }
}

// --- the companions' views ----------------------------------------------------------------------

// How each kind of part is drawn: registered by the companions' view modules (served from their
// packages, /views/<layout key>.js, loaded after this script), under the key the server lists those
// parts by in the layout. A view: {order, noun, tree(part), render(part), update(parts), alarms(parts),
// files(), statusPlain}; an ``overview`` view renders all its parts at once, above the others.
const VIEWS = [];
function registerView(key, view) {
  VIEWS.push({key, order: 100, ...view});
  VIEWS.sort((a, b) => a.order - b.order);
  if (view.statusPlain) Object.assign(STATUS_PLAIN, view.statusPlain);
}
const partsOf = (v) => (S.layout && S.layout[v.key]) || [];

function render() {
  const main = $("#cell");
  const kept = saveUi(main);
  main.textContent = "";
  const tree = $("#tree");
  tree.textContent = "";
  const list = el("ul");
  let shown = 0;
  for (const v of VIEWS.filter((x) => !x.overview)) {
    for (const part of partsOf(v)) {
      if (v.tree) list.append(v.tree(part));
      main.append(v.render(part));
      shown += 1;
    }
  }
  if (!shown) {
    const nouns = VIEWS.filter((v) => v.noun).map((v) => `no ${v.noun}`);
    main.append(el("p", {class: "muted", text: `This server offers ${nouns.join(" and ") || "nothing this page shows"}.`}));
  }
  for (const v of VIEWS.filter((x) => x.overview).reverse()) if (partsOf(v).length) main.prepend(v.render(partsOf(v)));
  tree.append(el("h2", {text: "Cell"}), list);
  main.append(el("section", {class: "card", id: "events"}, el("h2", {text: "Last transitions"}), el("ol", {id: "event-list"})));
  renderEvents();
  renderFiles();
  update();
  restoreUi(main, kept);
}

function renderFiles() {
  for (const v of VIEWS) if (v.files) v.files();
}

// Helpers the views share: a labelled state, a part's DI lock with its commands.
function stateLine(label, cls) {
  return el("div", {class: "state-line"}, el("span", {class: "label", text: label}), el("strong", {class: cls, text: "–"}));
}

function lockBox(lock, scopes) {
  if (!lock) return null;
  const note = el("span", {class: "lock-note", "data-lock-note": ""});
  note._locks = scopes;
  const mine = (r) => { if (r && r.good && r.outputs && r.outputs[0] === 0) S.myLocks.add(lock.variables.Locked); };
  const freed = (r) => { if (r && r.good) S.myLocks.delete(lock.variables.Locked); };
  return el("div", {class: "lock"}, el("span", {class: "label", text: "Lock"}), el("strong", {class: "v-lock", "data-key": lock.variables.Locked, text: "–"}),
    button("Lock", lock.methods.InitLock, {args: () => ["uacell web HMI"], after: mine}),
    button("Unlock", lock.methods.ExitLock, {after: freed}),
    button("Break lock", lock.methods.BreakLock, {cls: "danger", after: freed,
      confirm: "Break the lock another client holds? Its work on this part may be cut short."}), note);
}

function machineText(machine) {
  const s = S.values[machine.state];
  return s ?? "–";
}

function renderEvents() {
  const list = $("#event-list");
  if (!list) return;
  list.textContent = "";
  // Who: the user the server's AuditUpdateStateEvent names; "automatic" when the server audits and
  // sent none (the transition followed by itself); "—" when the server does not say.
  const auditing = !!(S.layout && S.layout.auditing);
  for (const e of S.events.slice(0, 15)) {
    const t = e.time ? new Date(e.time).toLocaleTimeString() : "";
    const reason = e.reason !== null && e.reason !== undefined ? ` (reason: ${e.reason})` : "";
    const who = e.user ? e.user : (auditing ? "automatic" : "—");
    list.append(el("li", {"data-user": e.user || ""}, el("time", {text: t}), ` ${e.machine}: ${e.from} → ${e.to} `,
      el("span", {class: e.user ? "ev-user" : "ev-user auto", title: e.method ? `called ${e.method}` : null, text: who}),
      reason));
  }
}

// Active alarms of the whole cell, in one banner above everything: what each view reports (robot
// conditions that are active or wait for an acknowledgement, PackML units' Admin.Alarm entries).
function activeAlarms() {
  return VIEWS.filter((v) => v.alarms).flatMap((v) => v.alarms(partsOf(v)));
}

function updateAlarmBanner() {
  const banner = $("#alarm");
  const alarms = activeAlarms();
  S.alarmActive = alarms.length > 0;
  banner.hidden = !alarms.length;
  banner.textContent = alarms.length ? `Alarm — ${alarms.join("; ")}` : "";
}

// DI locks of any part (lockBox): free, held by this session or locked by another.
function updateLocks() {
  for (const lock of $$(".v-lock")) {
    const locked = S.values[lock.dataset.key];
    const box = lock.closest(".lock");
    const note = lock.parentElement;
    lock.textContent = locked ? (S.myLocks.has(lock.dataset.key) ? "held by you" : "locked") : "free";
    note.dataset.locked = locked ? "true" : "false";
    if (!locked) S.myLocks.delete(lock.dataset.key);
    void box;
  }
}

function update() {
  if (!S.layout) return;
  for (const v of VIEWS) if (v.update) v.update(partsOf(v));
  updateLocks();
  updateAlarmBanner();
  updateButtons();
}

// --- login -------------------------------------------------------------------------------------

function openLogin(why) {
  $("#login-why").textContent = why || "Log in with a user of the OPC UA server.";
  $("#login-error").hidden = true;
  $("#login-password").value = "";
  if (!$("#login").open) $("#login").showModal();
}

async function submitLogin(ev) {
  ev.preventDefault();
  const user = $("#login-user").value.trim(), password = $("#login-password").value;
  $("#login-submit").disabled = true;
  try {
    const {status, data} = await api("/api/login", {user, password});
    $("#login-password").value = "";
    if (status === 200) {
      keepToken(data.csrf); S.user = data.user; S.myLocks.clear();
      $("#login").close();
      showUser();
      connect();
    } else {
      $("#login-error").textContent = data.error || `HTTP ${status}`;
      $("#login-error").hidden = false;
    }
  } finally {
    $("#login-submit").disabled = false;
  }
}

async function logout() {
  const {data} = await api("/api/logout", {});
  keepToken(data.csrf); S.user = null; S.myLocks.clear();
  showUser();
  connect();
}

// What the companions' view modules use of this page.
window.uacell = {
  S, $, $$, el, api, call, button, lockBox, stateLine, machineText, showResult, updateButtons, methodUsable,
  registerView,
};

window.addEventListener("DOMContentLoaded", async () => {
  $("#login-open").addEventListener("click", () => openLogin());
  $("#login-cancel").addEventListener("click", () => $("#login").close());
  $("#login-form").addEventListener("submit", submitLogin);
  $("#logout").addEventListener("click", logout);
  $("#viewer-close").addEventListener("click", () => $("#viewer").close());
  const s = await loadSession();
  S.user = s.user;
  showUser();
  connect();
});
