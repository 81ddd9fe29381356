// The web HMI's view of OPC 40010-1 robots (``Companion.web_view`` of uacell.robotics): each robot's
// controllers (SystemOperation, alarms, task controls, program files, locks) and motion devices.
// Loaded by the page as a module after app.js; draws what uacell.robotics.web_view describes.
const {S, $, $$, el, api, button, lockBox, stateLine, machineText, showResult, updateButtons, registerView} = window.uacell;

// What a non-zero Status of an operation method means, in words (beside its name, ROBOTICS_STATUS).
const STATUS_PLAIN = {
  E_SystemState: "the robot is not in a state that allows it", E_UnexpectedError: "the robot reported an error",
  E_ActiveAlarm: "an alarm is active", E_AcknowledgeRequired: "an alarm must be acknowledged first",
  "not found": "no program of that name", "invalid content": "the program is not valid",
  "unresolved reference": "the program calls a module that is not loaded: load the module first",
  "module in use": "a loaded program still uses this module",
};

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
  for (const box of $$(".device")) updateDevice(box);
}

// The tree beside the cell: a robot, its controllers with their task controls, its motion devices.
function tree(r) {
  const sub = el("ul");
  for (const c of r.controllers) {
    const tcs = el("ul");
    for (const t of c.task_controls) tcs.append(el("li", {}, el("a", {href: `#task-${r.name}-${t.name}`, text: t.name})));
    sub.append(el("li", {}, el("a", {href: `#ctrl-${r.name}-${c.name}`, text: c.name}), tcs));
  }
  for (const d of r.motion_devices) sub.append(el("li", {}, el("a", {href: `#dev-${r.name}-${d.name}`, text: d.name})));
  return el("li", {}, el("a", {href: `#robot-${r.name}`, text: `${r.name} (robot)`}), sub);
}

// Robot conditions that are active or wait for an acknowledgement (the page's alarm banner).
function alarms(robots) {
  const found = [];
  for (const r of robots) {
    for (const c of r.controllers) {
      for (const cond of c.conditions) {
        const v = cond.variables;
        const active = S.values[v["ActiveState/Id"]], acked = S.values[v["AckedState/Id"]];
        if (active) found.push(`${r.name}/${c.name}: ${cond.name} active${S.values[v.Message] ? ` (${S.values[v.Message]})` : ""}`);
        else if (acked === false) found.push(`${r.name}/${c.name}: ${cond.name} to acknowledge`);
      }
    }
  }
  return found;
}

registerView("robots", {
  order: 20, noun: "robot", tree, render: renderRobot, update: updateRobots, alarms, files: renderFiles,
  statusPlain: STATUS_PLAIN,
});

// The history view of a robot (uacell.robotics.web_view.robot_history): each task control's program runs.
const HIST = window.uacellHistory;

function robotHistory(r, range) {
  const art = HIST.el("article", { class: "hist-robot", "data-robot": r.name });
  art.appendChild(HIST.el("h3", {}, r.name));
  for (const t of r.tasks) {
    art.appendChild(HIST.el("h4", {}, `${t.task}: program runs`));
    art.append(HIST.bar(t.runs, range, `${t.task} program runs`), HIST.axis(range));
    const list = HIST.el("ul", { class: "hist-runs" });
    if (!t.runs.length) list.appendChild(HIST.el("li", { class: "muted" }, "no program ran in this range"));
    for (const run of t.runs.slice().reverse().slice(0, 20)) {
      list.appendChild(HIST.el("li", { "data-program": run.label }, `${run.label}: ${HIST.clock(run.start)} to ${HIST.clock(run.end)} (${HIST.span(run.seconds)})`));
    }
    art.appendChild(list);
  }
  return art;
}

function mergeRobot(o = { tasks: [] }, r, from) {
  const tasks = r.tasks.map((t) => {
    const ot = o.tasks.find((x) => x.task === t.task) || { runs: [] };
    return { ...t, runs: HIST.joinSegments(ot.runs, t.runs, from) };
  });
  return { ...r, tasks };
}

HIST.register("robots", { order: 20, view: robotHistory, merge: mergeRobot });
