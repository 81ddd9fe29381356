// The web HMI's view of PackML units (``Companion.web_view`` of uacell.packml): the ISA-TR88 state
// model, the commands, Status and Admin, start parameters, speed and unit mode of each unit.
// Loaded by the page as a module after app.js; draws what uacell.packml.web_view describes.
const {S, $, $$, el, api, button, lockBox, stateLine, machineText, showResult, updateButtons, registerView} = window.uacell;

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

function tree(u) {
  return el("li", {}, el("a", {href: `#unit-${u.name}`, text: `${u.name} (PackML unit)`}));
}

// A unit's Admin.Alarm entries (the page's alarm banner).
function alarms(units) {
  const found = [];
  for (const u of units) {
    const list = S.values[u.variables.Alarm] || [];
    for (const a of list) found.push(`${u.name}: ${a.Message || a.ID}`);
  }
  return found;
}

registerView("units", {
  order: 10, noun: "PackML unit", tree, render: renderUnit, alarms,
  update: (units) => { for (const u of units) updateUnit(u); },
});

// The history view of a unit (uacell.packml.web_view.unit_history): OEE figures, the state timeline,
// speed and count trends, the states newest first.
const HIST = window.uacellHistory;

function unitHistory(u, range) {
  const art = HIST.el("article", { class: "hist-unit", "data-unit": u.name });
  art.appendChild(HIST.el("h3", {}, `${u.name}`));
  const oee = HIST.el("dl", { class: "oee" });
  for (const name of ["Availability", "Performance", "Quality", "OEE"]) {
    const item = HIST.el("div", { "data-figure": name });
    item.append(HIST.el("dt", {}, name), HIST.el("dd", {}, HIST.pct(u.oee[name])));
    oee.appendChild(item);
  }
  art.appendChild(oee);
  art.appendChild(HIST.el("h4", {}, "State timeline"));
  art.append(HIST.bar(u.timeline, range, `${u.name} states`), HIST.axis(range));
  art.appendChild(HIST.trend({ MachSpeed: u.trends.MachSpeed || [], CurMachSpeed: u.trends.CurMachSpeed || [] }, range, "Speed (packages/min)", true));
  art.appendChild(HIST.trend({ Processed: u.trends.ProdProcessedCount || [], Defective: u.trends.ProdDefectiveCount || [] }, range, "Counts", true));
  art.appendChild(HIST.stateTable(u.timeline));
  return art;
}

function mergeUnit(o = { timeline: [], trends: {}, oee: {} }, u, from, column) {
  const trends = {};
  for (const [k, pts] of Object.entries(u.trends)) trends[k] = HIST.joinPoints(o.trends[k], pts, from, column);
  const oee = { ...u.oee };
  if (u.oee.trend) oee.trend = HIST.joinPoints((o.oee || {}).trend, u.oee.trend, from, column);
  return { ...u, timeline: HIST.joinSegments(o.timeline, u.timeline, from), trends, oee };
}

HIST.register("units", { order: 10, view: unitHistory, merge: mergeUnit });
