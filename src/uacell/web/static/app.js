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
const STATUS_PLAIN = {
  E_SystemState: "the robot is not in a state that allows it", E_UnexpectedError: "the robot reported an error",
  E_ActiveAlarm: "an alarm is active", E_AcknowledgeRequired: "an alarm must be acknowledged first",
  "not found": "no program of that name", "invalid content": "the program is not valid",
  "unresolved reference": "the program calls a module that is not loaded: load the module first",
  "module in use": "a loaded program still uses this module",
};

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

function render() {
  const main = $("#cell");
  const kept = saveUi(main);
  main.textContent = "";
  const tree = $("#tree");
  tree.textContent = "";
  const L = S.layout || {robots: [], units: []};
  const list = el("ul");
  for (const u of L.units) {
    list.append(el("li", {}, el("a", {href: `#unit-${u.name}`, text: `${u.name} (PackML unit)`})));
    main.append(renderUnit(u));
  }
  for (const r of L.robots) {
    const sub = el("ul");
    for (const c of r.controllers) {
      const tcs = el("ul");
      for (const t of c.task_controls) tcs.append(el("li", {}, el("a", {href: `#task-${r.name}-${t.name}`, text: t.name})));
      sub.append(el("li", {}, el("a", {href: `#ctrl-${r.name}-${c.name}`, text: c.name}), tcs));
    }
    for (const d of r.motion_devices) sub.append(el("li", {}, el("a", {href: `#dev-${r.name}-${d.name}`, text: d.name})));
    list.append(el("li", {}, el("a", {href: `#robot-${r.name}`, text: `${r.name} (robot)`}), sub));
    main.append(renderRobot(r));
  }
  if (!L.units.length && !L.robots.length) main.append(el("p", {class: "muted", text: "This server offers no robot and no PackML unit."}));
  if ((L.machines || []).length) main.prepend(renderMachines(L.machines));
  tree.append(el("h2", {text: "Cell"}), list);
  main.append(el("section", {class: "card", id: "events"}, el("h2", {text: "Last transitions"}), el("ol", {id: "event-list"})));
  renderEvents();
  renderFiles();
  update();
  restoreUi(main, kept);
}

// PackML: the ISA-TR88 state model in its familiar layout. Acting states (ending by themselves) are
// drawn apart from wait states; Execute is the producing state.
const TR88 = {
  Unholding: [1, 0, "acting"], Held: [2, 0, "wait"], Holding: [3, 0, "acting"],
  Idle: [0, 1, "wait"], Starting: [1, 1, "acting"], Execute: [2, 1, "execute"], Completing: [3, 1, "acting"], Complete: [4, 1, "wait"],
  Resetting: [0, 2, "acting"], Unsuspending: [1, 2, "acting"], Suspended: [2, 2, "wait"], Suspending: [3, 2, "acting"],
  Stopped: [0, 3, "wait"], Stopping: [4, 3, "acting"],
  Clearing: [0, 4, "acting"], Aborted: [2, 4, "wait"], Aborting: [4, 4, "acting"],
};
const W = 120, H = 44, GX = 176, GY = 84, PAD = 16;  // room between boxes for a whole label
const box = (s) => [PAD + TR88[s][0] * GX, PAD + TR88[s][1] * GY];
const center = (s) => { const [x, y] = box(s); return [x + W / 2, y + H / 2]; };
const LANE = PAD + 2 * GY + H + (GY - H) / 2;  // between the suspend row and the stopped row
// [from, to, command label, route]: a route is a list of points between the two boxes.
const ARROWS = [
  ["Idle", "Starting", "Start"], ["Starting", "Execute", ""], ["Execute", "Completing", ""],
  ["Completing", "Complete", ""], ["Resetting", "Idle", ""],
  ["Complete", "Resetting", "Reset", () => {
    const [cx, cy] = box("Complete"), [rx, ry] = box("Resetting");
    return [[cx + W / 2, cy + H], [cx + W / 2, LANE], [rx + W * 0.75, LANE], [rx + W * 0.75, ry + H]];
  }],
  ["Execute", "Holding", "Hold"], ["Holding", "Held", ""], ["Held", "Unholding", "Unhold"], ["Unholding", "Execute", ""],
  ["Execute", "Suspending", "Suspend"], ["Suspending", "Suspended", ""], ["Suspended", "Unsuspending", "Unsuspend"],
  ["Unsuspending", "Execute", ""], ["Stopped", "Resetting", "Reset"], ["Stopping", "Stopped", ""],
  ["Aborting", "Aborted", ""], ["Aborted", "Clearing", "Clear"], ["Clearing", "Stopped", ""],
];

// Where the straight line from the centre of state a towards point (x, y) leaves a's box.
function edgePoint(a, x, y) {
  const [cx, cy] = center(a);
  const dx = x - cx, dy = y - cy;
  const k = Math.min(W / 2 / Math.abs(dx || 1e-9), H / 2 / Math.abs(dy || 1e-9));
  return [cx + dx * k, cy + dy * k];
}

function diagram(unit) {
  const svg = el("svg:svg", {viewBox: `0 0 ${PAD * 2 + 4 * GX + W} ${PAD * 2 + 4 * GY + H + 20}`, class: "tr88",
                             "data-unit": unit.name, role: "img", "aria-label": `${unit.name} PackML state`});
  const defs = el("svg:defs");
  const marker = el("svg:marker", {id: `arrow-${unit.name}`, viewBox: "0 0 10 10", refX: "10", refY: "5",
                                   markerWidth: "7", markerHeight: "7", orient: "auto-start-reverse"});
  marker.append(el("svg:path", {d: "M 0 0 L 10 5 L 0 10 z", class: "arrowhead"}));
  defs.append(marker);
  svg.append(defs);
  const labels = [];
  for (const [a, b, label, route] of ARROWS) {
    let points;
    if (route) points = route();
    else {
      const [ax, ay] = center(a), [bx, by] = center(b);
      points = [edgePoint(a, bx, by), edgePoint(b, ax, ay)];
    }
    svg.append(el("svg:polyline", {points: points.map((p) => p.map((v) => v.toFixed(1)).join(",")).join(" "),
                                   class: "edge", "marker-end": `url(#arrow-${unit.name})`}));
    if (label) {
      const i = Math.floor((points.length - 1) / 2);
      const [x1, y1] = points[i], [x2, y2] = points[i + 1];
      let y = (y1 + y2) / 2 - 5;
      if (y1 === y2 && Math.abs(x2 - x1) < label.length * 10) {
        // A short horizontal edge between two boxes has no room for its word: it goes in the gap
        // between this row and the Execute row instead, clear of every box.
        y = y1 < center("Execute")[1] ? y1 + H / 2 + 20 : y1 - H / 2 - 8;
      }
      labels.push(el("svg:text", {x: (x1 + x2) / 2 + (x1 === x2 ? 6 : 0), y,
                                  class: `edge-label${x1 === x2 ? " side" : ""}`, text: label}));
    }
  }
  for (const [name, [, , kind]] of Object.entries(TR88)) {
    const [x, y] = box(name);
    const g = el("svg:g", {class: `state ${kind}`, "data-state": name});
    g.append(el("svg:rect", {x, y, width: W, height: H, rx: kind === "wait" ? 4 : 18}));
    g.append(el("svg:text", {x: x + W / 2, y: y + H / 2 + 5, text: name}));
    svg.append(g);
  }
  svg.append(...labels);  // over the boxes and lines, never hidden by them
  const note = (y, text) => svg.append(el("svg:text", {x: PAD + GX + W / 2, y, class: "legend", text}));
  note(PAD + 3 * GY + H + 12, "Stop (from any state but Aborting/Aborted/Clearing) → Stopping");
  note(PAD + 3 * GY + H + 26, "Abort (from any state but Aborting/Aborted) → Aborting");
  svg.append(el("svg:text", {x: PAD, y: PAD * 2 + 4 * GY + H + 14, class: "legend",
                             text: "rounded: acting state (ends by itself)   square: wait state (needs a command)"}));
  return svg;
}

// On a narrow screen the diagram gives way to this list: every TR88 state, the current one marked.
function stateList(unit) {
  return el("ol", {class: "state-list", "data-unit": unit.name, "aria-label": `${unit.name} PackML states`},
    ...Object.keys(TR88).map((name) => el("li", {"data-state": name, text: name})));
}

function unitState(unit) {
  let state = null;
  for (const m of unit.machines) {
    const v = S.values[m.state];
    if (v && v !== "Cleared" && v !== "Running") state = v;
    else if (v === null || v === undefined) break;
  }
  return state;
}

const MODES = {0: "Invalid", 1: "Produce", 2: "Maintenance", 3: "Manual"};

function renderUnit(u) {
  const m = Object.fromEntries(u.machines.map((x) => [x.name, x.methods]));
  const base = m.BaseStateMachine || {}, machine = m.MachineState || {}, exec = m.ExecuteState || {};
  const keys = (...ks) => ks.filter(Boolean);
  const commands = el("div", {class: "commands"},
    button("Reset", machine.Reset, {keys: keys(machine.Reset, exec.Reset)}),
    button("Start", exec.Start, {args: () => [startParameters(u)]}),
    button("Stop", machine.Stop), button("Hold", exec.Hold), button("Unhold", exec.Unhold),
    button("Suspend", exec.Suspend), button("Unsuspend", exec.Unsuspend), button("Complete", exec.ToComplete),
    button("Abort", base.Abort, {cls: "danger", confirm: `Abort ${u.name}? It stops at once, mid-cycle.`}),
    button("Clear", base.Clear));
  for (const b of $$("button", commands)) b._state = () => unitState(u);
  const paramRows = el("tbody", {class: "param-rows"});
  const addRow = (id = "", name = "", unit = "", value = "") => {
    paramRows.append(el("tr", {},
      el("td", {}, el("input", {class: "p-id", type: "number", value: id, "aria-label": "ID"})),
      el("td", {}, el("input", {class: "p-name", value: name, "aria-label": "Name"})),
      el("td", {}, el("input", {class: "p-unit", value: unit, "aria-label": "Unit"})),
      el("td", {}, el("input", {class: "p-value", type: "number", step: "any", value: value, "aria-label": "Value"})),
      el("td", {}, el("button", {type: "button", class: "small", onclick: (e) => e.target.closest("tr").remove(), text: "×"}))));
  };
  const params = el("details", {class: "params"}, el("summary", {text: "Start parameters"}),
    el("table", {}, el("thead", {}, el("tr", {}, ...["ID", "Name", "Unit", "Value", ""].map((t) => el("th", {text: t})))), paramRows),
    el("button", {type: "button", class: "small add-param", onclick: () => addRow(), text: "+ parameter"}));
  const speed = el("input", {type: "number", step: "any", class: "speed-input", id: `speed-${u.name}`});
  const mode = el("select", {class: "mode-input", "aria-label": "unit mode"},
    ...[1, 2, 3].map((v) => el("option", {value: v, text: MODES[v]})));
  const unitControls = el("div", {class: "commands"},
    el("label", {for: `speed-${u.name}`, class: "speed-label", text: "Speed (MachSpeed)"}), speed,
    el("span", {class: "unit-text", text: "packages/min"}),
    button("Set speed", u.methods.SetMachSpeed, {args: () => [Number(speed.value)], explain: () => {
      const range = S.values[u.variables.MachSpeedRange];
      return range ? `speed must be within ${range.Low}..${range.High} packages/min` : "";
    }}),
    mode, button("Set mode", u.methods.SetUnitMode, {args: () => [Number(mode.value)]}));
  for (const b of $$("button", unitControls)) b._state = () => unitState(u);
  const facts = el("dl", {class: "facts"});
  const fact = (label, cls) => facts.append(el("dt", {text: label}), el("dd", {class: cls, text: "–"}));
  fact("State", "v-state"); fact("Unit mode", "v-mode"); fact("MachSpeed", "v-machspeed");
  fact("CurMachSpeed", "v-curmachspeed"); fact("Produced", "v-processed"); fact("Defective", "v-defective");
  fact("Stop reason", "v-stopreason"); fact("Alarms", "v-alarms"); fact("Start parameters used", "v-startparams");
  return el("section", {class: "card unit", id: `unit-${u.name}`, "data-unit": u.name},
    el("h2", {text: `${u.name}: PackML unit`}),
    el("p", {class: "hint", text: "To produce: Reset, then Start (the counts grow in Execute). Complete ends the "
      + "batch, Reset again for the next; Hold/Suspend pause it; Stop or Abort at any time, Clear after an Abort."}),
    el("div", {class: "unit-grid"}, diagram(u), stateList(u), el("div", {}, facts)),
    commands, params, unitControls);
}

function startParameters(u) {
  const card = $(`section.unit[data-unit="${u.name}"]`);
  return $$(".param-rows tr", card).map((tr) => ({
    ID: Number($(".p-id", tr).value), Name: $(".p-name", tr).value, Unit: $(".p-unit", tr).value,
    Value: Number($(".p-value", tr).value),
  }));
}

const unitName = (u) => {
  const name = u && typeof u === "object" ? u.DisplayName : u;
  return name ? ` ${name}` : "";
};
const first = (v) => (Array.isArray(v) ? v[0] : v);
const fmt = (v, digits = 1) => (typeof v === "number" ? v.toFixed(digits) : (v ?? "–"));

function updateUnit(u) {
  const card = $(`section.unit[data-unit="${u.name}"]`);
  if (!card) return;
  const state = unitState(u);
  for (const g of $$("g.state", card)) g.classList.toggle("current", g.dataset.state === state);
  for (const li of $$(".state-list li", card)) {
    li.classList.toggle("current", li.dataset.state === state);
    if (li.dataset.state === state) li.setAttribute("aria-current", "step"); else li.removeAttribute("aria-current");
  }
  const v = (name) => S.values[u.variables[name]];
  const set = (cls, text) => { const e = $(`.${cls}`, card); if (e) e.textContent = text; };
  set("v-state", state || "–");
  set("v-mode", MODES[v("UnitModeCurrent")] || fmt(v("UnitModeCurrent")));
  set("v-machspeed", fmt(v("MachSpeed")));
  set("v-curmachspeed", fmt(v("CurMachSpeed")));
  const count = (x) => { const c = first(x); return c ? String(c.Count) : "–"; };
  set("v-processed", count(v("ProdProcessedCount")));
  set("v-defective", count(v("ProdDefectiveCount")));
  const reason = first(v("StopReason"));
  set("v-stopreason", reason && (reason.Message || reason.ID) ? `${reason.Message || ""} (${reason.ID})` : "–");
  const alarms = v("Alarm") || [];
  set("v-alarms", alarms.length ? alarms.map((a) => a.Message || a.ID).join("; ") : "none");
  const params = v("StartParameters") || [];
  set("v-startparams", params.length ? params.map((p) => `${p.Name || p.ID} = ${p.Value}${unitName(p.Unit)}`).join(", ") : "none");
  const speed = $(".speed-input", card);
  if (speed && document.activeElement !== speed && !speed.value) speed.value = v("MachSpeed") ?? "";
}

// Robots ----------------------------------------------------------------------------------------

function stateLine(label, cls) {
  return el("div", {class: "state-line"}, el("span", {class: "label", text: label}), el("strong", {class: cls, text: "–"}));
}

// The loaded program and, while an instruction executes, its source line (where the server says it).
function programLine() {
  const line = stateLine("Program", "v-program");
  line.append(el("span", {class: "v-line", hidden: true}));
  return line;
}

function renderRobot(r) {
  const card = el("section", {class: "card robot", id: `robot-${r.name}`, "data-robot": r.name}, el("h2", {text: `${r.name}: robot`}));
  for (const c of r.controllers) card.append(renderController(r, c));
  for (const d of r.motion_devices) card.append(renderDevice(r, d));
  return card;
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

function renderController(r, c) {
  const so = c.system_operation;
  const ctrlLocks = [c.lock];
  const box = el("div", {class: "controller", id: `ctrl-${r.name}-${c.name}`, "data-controller": c.name},
    el("h3", {text: c.name}),
    el("p", {class: "hint", text: "To run a program: Get ready (drives on), choose a program below and Load it; "
      + "a program that uses a module (pick_and_place and palletize use gripper) needs the module loaded too: "
      + "choose gripper and Load it; then Start. Stop pauses, Stand down switches the drives off."}),
    stateLine("SystemOperation", "v-sysop"),
    lockBox(c.lock, [c.lock]),
    el("div", {class: "commands"},
      button("Get ready", so.methods.GetReady, {locks: ctrlLocks}), button("Stand down", so.methods.StandDown, {locks: ctrlLocks}),
      button("Start all", so.methods.Start, {locks: ctrlLocks}), button("Stop all", so.methods.Stop, {locks: ctrlLocks, args: () => [0]})));
  box._so = so;
  const conds = el("div", {class: "conditions"}, el("h4", {text: "Alarms"}));
  for (const cond of c.conditions) {
    const row = el("div", {class: "condition", "data-condition": cond.name},
      el("span", {class: "c-name", text: cond.name}), el("span", {class: "c-state", text: "–"}),
      button("Acknowledge", cond.methods.Acknowledge, {args: () => [S.values[cond.variables.EventId] || "", "acknowledged in the web HMI"]}));
    row._cond = cond;
    conds.append(row);
  }
  if (c.simulate_alarm) {
    conds.append(el("div", {class: "commands"},
      button("Simulate emergency stop", c.simulate_alarm, {args: () => ["EmergencyStop", true]}),
      button("Release emergency stop", c.simulate_alarm, {args: () => ["EmergencyStop", false]})));
  }
  box.append(conds);
  for (const t of c.task_controls) box.append(renderTask(r, c, t));
  if (c.programs) box.append(renderPrograms(c));
  return box;
}

function renderTask(r, c, t) {
  const locks = [c.lock, t.lock];
  const select = el("select", {class: "program-select", "aria-label": "program to load", "data-directory": c.programs || ""});
  const m = t.methods;
  const box = el("div", {class: "task", id: `task-${r.name}-${t.name}`, "data-task": t.name},
    el("h4", {text: `Task control ${t.name}`}),
    stateLine("State", "v-task"), programLine(), stateLine("Modules", "v-modules"),
    lockBox(t.lock, [t.lock, c.lock]),
    el("div", {class: "commands"}, select,
      button("Load", m.LoadByName, {locks, args: () => [select.value.replace(/\.robot$/, "")]}),
      button("Unload", m.UnloadProgram, {locks}), button("Start", m.Start, {locks, why: () => {
        // Ready with a program and still no Start: what the program uses is missing (Status -3 on a call).
        const ready = S.values[t.state] === "Ready" && S.values[t.variables.TaskProgramName];
        return ready ? "the program uses a module that is not loaded: load it first (see the hint above)" : "";
      }}),
      button("Stop", m.Stop, {locks, args: () => [0]}), button("To program start", m.ResetToProgramStart, {locks})));
  box._task = t;
  return box;
}

// A button for a file operation: enabled as the directory method it uses (CreateFile, Delete) is.
function fileButton(label, key, cls) {
  const b = el("button", {type: "button", class: cls, "data-method": key || "", text: label});
  b._keys = key ? [key] : [];
  b._locks = [];
  return b;
}

function renderPrograms(c) {
  const name = el("input", {class: "upload-name", placeholder: "name.robot", "aria-label": "file name"});
  const text = el("textarea", {class: "upload-text", rows: 6, placeholder: "program Name\nmove 0 0 0 0 0 0", "aria-label": "program text"});
  const upload = fileButton("Upload", (c.program_methods || {}).CreateFile, "upload");
  upload.addEventListener("click", async () => {
    const {status, data} = await api("/api/upload", {directory: c.programs, path: name.value.trim(), content: text.value});
    showResult(`Upload ${name.value}`, status === 200 ? data : {good: false, code: data.error});
  });
  const box = el("div", {class: "programs", "data-directory": c.programs},
    el("h4", {text: "Program files"}), el("ul", {class: "file-list"}),
    el("details", {class: "upload-box"}, el("summary", {text: "Upload a program (engineers)"}), name, text, upload));
  box._deleteKey = (c.program_methods || {}).Delete;
  return box;
}

function renderFiles() {
  for (const box of $$(".programs[data-directory]")) {
    const dir = box.dataset.directory;
    const list = $(".file-list", box);
    list.textContent = "";
    for (const f of S.files[dir] || []) {
      const view = el("button", {type: "button", class: "small", text: "View"});
      if (f.viewable === false) {
        view.disabled = true;
        view.title = `View: your role may not read program files (${S.user || "anonymous"})`;
      }
      view.addEventListener("click", async () => {
        const {status, data} = await api("/api/file", {directory: dir, path: f.path});
        if (status === 200 && data.content !== undefined) {
          $("#viewer-title").textContent = f.path; $("#viewer-text").textContent = data.content; $("#viewer").showModal();
        } else showResult(`View ${f.path}`, status === 200 ? data : {good: false, code: data.error});
      });
      const del = fileButton("Delete", box._deleteKey, "small danger");
      del.addEventListener("click", async () => {
        if (!window.confirm(`Delete ${f.path}? This cannot be undone.`)) return;
        const {status, data} = await api("/api/delete", {directory: dir, path: f.path});
        showResult(`Delete ${f.path}`, status === 200 ? data : {good: false, code: data.error});
      });
      list.append(el("li", {"data-file": f.path}, el("span", {text: f.path}), view, del));
    }
  }
  updateButtons();
  for (const sel of $$("select.program-select")) {
    const keep = sel.value;
    sel.textContent = "";
    for (const f of S.files[sel.dataset.directory] || []) sel.append(el("option", {value: f.path, text: f.path}));
    if (keep) sel.value = keep;
  }
}

function renderDevice(r, d) {
  const svg = el("svg:svg", {viewBox: "-170 -170 340 200", class: "arm", role: "img", "aria-label": `${d.name} arm`});
  svg.append(el("svg:line", {x1: -160, y1: 20, x2: 160, y2: 20, class: "floor"}));
  svg.append(el("svg:polyline", {class: "links", points: "0,20 0,-30"}));
  svg.append(el("svg:circle", {class: "tool", cx: 0, cy: -30, r: 6}));
  const table = el("table", {class: "axes"}, el("tbody", {},
    ...d.axes.map((a) => el("tr", {"data-axis": a.name}, el("th", {text: a.name}), el("td", {class: "pos", text: "–"}),
      el("td", {}, el("div", {class: "bar"}, el("div", {class: "fill"})))))));
  const box = el("div", {class: "device", id: `dev-${r.name}-${d.name}`, "data-device": d.name},
    el("h3", {text: `${d.name}: axis positions (degrees)`}), el("div", {class: "device-grid"}, svg, table));
  box._device = d;
  return box;
}

const RAD = Math.PI / 180;

function updateDevice(box) {
  const d = box._device;
  const pos = d.axes.map((a) => S.values[a.position]);
  d.axes.forEach((a, i) => {
    const row = $(`tr[data-axis="${a.name}"]`, box);
    const v = pos[i];
    $(".pos", row).textContent = typeof v === "number" ? v.toFixed(1) : "–";
    const fill = $(".fill", row);
    const pct = typeof v === "number" ? Math.max(-100, Math.min(100, v / 1.8)) : 0;
    fill.style.width = `${Math.abs(pct) / 2}%`;
    fill.style.marginLeft = pct < 0 ? `${50 - Math.abs(pct) / 2}%` : "50%";
  });
  // A side view of the first three axes: A2 tilts the upper arm from vertical, A3 the forearm.
  const a2 = (pos[1] || 0) * RAD, a3 = (pos[2] || 0) * RAD;
  const x1 = 0, y1 = -30, l1 = 80, l2 = 70;
  const x2 = x1 + l1 * Math.sin(a2), y2 = y1 - l1 * Math.cos(a2);
  const x3 = x2 + l2 * Math.sin(a2 + a3 + Math.PI / 2), y3 = y2 - l2 * Math.cos(a2 + a3 + Math.PI / 2);
  $("polyline.links", box).setAttribute("points", `0,20 ${x1},${y1} ${x2.toFixed(1)},${y2.toFixed(1)} ${x3.toFixed(1)},${y3.toFixed(1)}`);
  const tool = $("circle.tool", box);
  tool.setAttribute("cx", x3.toFixed(1)); tool.setAttribute("cy", y3.toFixed(1));
}

function machineText(machine) {
  const s = S.values[machine.state];
  return s ?? "–";
}

function updateRobots() {
  for (const box of $$(".controller")) {
    const so = box._so;
    let text = machineText(so);
    for (const sub of so.substates) if (S.values[sub.state]) text += ` / ${S.values[sub.state]}`;
    $(".v-sysop", box).textContent = text;
    for (const row of $$(".condition", box)) {
      const v = row._cond.variables;
      const active = S.values[v["ActiveState/Id"]], acked = S.values[v["AckedState/Id"]];
      const c = $(".c-state", row);
      c.textContent = active ? "ACTIVE" : (acked === false ? "inactive, not acknowledged" : "ok");
      row.dataset.active = active ? "true" : "false";
      row.title = S.values[v.Message] || "";
    }
  }
  for (const box of $$(".task")) {
    const t = box._task;
    let text = machineText(t);
    if (S.values[t.ready.state]) text += ` / ${S.values[t.ready.state]}`;
    $(".v-task", box).textContent = text;
    $(".v-program", box).textContent = S.values[t.variables.TaskProgramName] || "none";
    const line = t.variables.CurrentLine ? S.values[t.variables.CurrentLine] : null;
    const lineBox = $(".v-line", box);
    lineBox.textContent = line ? `line ${line}` : "";
    lineBox.hidden = !line;
    $(".v-modules", box).textContent = (S.modules[t.modules] || []).join(", ") || "none";
  }
  for (const lock of $$(".v-lock")) {
    const locked = S.values[lock.dataset.key];
    const box = lock.closest(".lock");
    const note = lock.parentElement;
    lock.textContent = locked ? (S.myLocks.has(lock.dataset.key) ? "held by you" : "locked") : "free";
    note.dataset.locked = locked ? "true" : "false";
    if (!locked) S.myLocks.delete(lock.dataset.key);
    void box;
  }
  for (const box of $$(".device")) updateDevice(box);
}

// OPC 40001-1 machines (Objects/Machines): one tile each with MachineryItemState and MachineryOperationMode.
function renderMachines(machines) {
  const tiles = machines.map((m) => {
    const ident = ["Manufacturer", "Model", "SerialNumber", "Location"].filter((n) => m.identification[n]);
    const tile = el("div", {class: "machine-tile", "data-machine": m.name},
      el("h3", {text: m.name}),
      el("div", {}, "State ", el("strong", {class: "m-state", text: "–"})),
      el("div", {}, "Mode ", el("strong", {class: "m-mode", text: "–"})),
      el("div", {class: "m-ident muted"}));
    tile._machine = m; tile._ident = ident;
    return tile;
  });
  return el("section", {class: "card", id: "machines"}, el("h2", {text: "Machines"}), el("div", {class: "machine-tiles"}, ...tiles));
}

function updateMachines() {
  for (const tile of $$(".machine-tile")) {
    const m = tile._machine;
    const state = m.state && m.state.state ? machineText(m.state) : "–";
    $(".m-state", tile).textContent = state;
    tile.dataset.state = state;
    $(".m-mode", tile).textContent = m.mode && m.mode.state ? machineText(m.mode) : "–";
    $(".m-ident", tile).textContent = tile._ident.map((n) => S.values[m.identification[n]]).filter((v) => v).join(" · ");
  }
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

// Active alarms of the whole cell, in one banner above everything: robot conditions that are active
// (or wait for an acknowledgement) and PackML units' Admin.Alarm entries.
function activeAlarms() {
  const found = [];
  for (const r of S.layout.robots) {
    for (const c of r.controllers) {
      for (const cond of c.conditions) {
        const v = cond.variables;
        const active = S.values[v["ActiveState/Id"]], acked = S.values[v["AckedState/Id"]];
        if (active) found.push(`${r.name}/${c.name}: ${cond.name} active${S.values[v.Message] ? ` (${S.values[v.Message]})` : ""}`);
        else if (acked === false) found.push(`${r.name}/${c.name}: ${cond.name} to acknowledge`);
      }
    }
  }
  for (const u of S.layout.units) {
    const alarms = S.values[u.variables.Alarm] || [];
    for (const a of alarms) found.push(`${u.name}: ${a.Message || a.ID}`);
  }
  return found;
}

function updateAlarmBanner() {
  const banner = $("#alarm");
  const alarms = activeAlarms();
  S.alarmActive = alarms.length > 0;
  banner.hidden = !alarms.length;
  banner.textContent = alarms.length ? `Alarm — ${alarms.join("; ")}` : "";
}

function update() {
  if (!S.layout) return;
  for (const u of S.layout.units) updateUnit(u);
  updateRobots();
  updateMachines();
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
