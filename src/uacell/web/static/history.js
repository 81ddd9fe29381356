// The history view (docs/web.md, "History"): what each companion's view module draws of its parts
// (per PackML unit a state timeline, speed and count trends and the OEE figures; per robot the
// program runs), in its order. Plain SVG, data from GET /api/history:
// whole at first, then every 15 s only what is new (since=), trends as one value per pixel column.
"use strict";
(() => {
  const SVGNS = "http://www.w3.org/2000/svg";
  const W = 1000;
  const COLORS = {
    Execute: "#2e7d32", Executing: "#2e7d32",
    Stopped: "#c62828", Aborted: "#c62828", Aborting: "#e57373", Stopping: "#e57373", Clearing: "#ef9a9a",
    Held: "#f9a825", Holding: "#fbc02d", Unholding: "#fdd835",
    Suspended: "#ef6c00", Suspending: "#fb8c00", Unsuspending: "#ffa726",
    Idle: "#1565c0", Resetting: "#42a5f5", Starting: "#64b5f6", Complete: "#5c6bc0", Completing: "#7986cb",
  };
  const $ = (id) => document.getElementById(id);

  function el(tag, attrs = {}, text) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text !== undefined) e.textContent = text;
    return e;
  }
  function svg(tag, attrs = {}) {
    const e = document.createElementNS(SVGNS, tag);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
    return e;
  }
  const clock = (t) => new Date(t * 1000).toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit" });
  function span(seconds) {
    const s = Math.round(seconds);
    if (s < 60) return `${s} s`;
    if (s < 3600) return `${Math.floor(s / 60)} min ${s % 60} s`;
    return `${Math.floor(s / 3600)} h ${Math.floor((s % 3600) / 60)} min`;
  }
  const pct = (x) => (typeof x === "number" ? `${(x * 100).toFixed(1)} %` : "–");

  function bar(segments, range, label) {
    const box = svg("svg", { viewBox: `0 0 ${W} 34`, class: "hist-bar", role: "img", "aria-label": label, preserveAspectRatio: "none" });
    const x = (t) => ((t - range.start) / (range.end - range.start)) * W;
    for (const seg of segments) {
      const r = svg("rect", {
        x: x(seg.start).toFixed(2), y: 2, height: 30,
        width: Math.max(0.5, x(seg.end) - x(seg.start)).toFixed(2),
        fill: COLORS[seg.label] || "#78909c", "data-state": seg.label,
      });
      const title = svg("title");
      title.textContent = `${seg.label}: ${clock(seg.start)} to ${clock(seg.end)} (${span(seg.seconds)})`;
      r.appendChild(title);
      box.appendChild(r);
    }
    return box;
  }

  function axis(range) {
    const row = el("div", { class: "hist-axis" });
    row.append(el("span", {}, clock(range.start)), el("span", {}, clock(range.end)));
    return row;
  }

  function trend(series, range, label, stepped) {
    const box = svg("svg", { viewBox: `0 0 ${W} 120`, class: "hist-trend", role: "img", "aria-label": label, preserveAspectRatio: "none" });
    const all = Object.values(series).flat();
    if (!all.length) return el("p", { class: "muted" }, `${label}: no values in this range`);
    let lo = Math.min(...all.map((p) => p[1]));
    let hi = Math.max(...all.map((p) => p[1]));
    if (hi === lo) { hi += 1; lo -= lo > 0 ? 1 : 0; }
    const x = (t) => ((t - range.start) / (range.end - range.start)) * W;
    const y = (v) => 115 - ((v - lo) / (hi - lo)) * 110;
    const palette = ["#1565c0", "#2e7d32", "#c62828", "#6a1b9a"];
    const legend = el("div", { class: "hist-legend" });
    Object.entries(series).forEach(([name, points], i) => {
      if (!points.length) return;
      const pts = [];
      points.forEach(([t, v], k) => {
        if (stepped && k > 0) pts.push(`${x(t).toFixed(1)},${y(points[k - 1][1]).toFixed(1)}`);
        pts.push(`${x(t).toFixed(1)},${y(v).toFixed(1)}`);
      });
      pts.push(`${W},${y(points[points.length - 1][1]).toFixed(1)}`);
      box.appendChild(svg("polyline", { points: pts.join(" "), fill: "none", stroke: palette[i % palette.length], "stroke-width": 2, "vector-effect": "non-scaling-stroke", "data-series": name }));
      const key = el("span", { "data-series": name }, `■ ${name} (now ${points[points.length - 1][1]})`);
      key.style.color = palette[i % palette.length];
      legend.appendChild(key);
    });
    const wrap = el("figure", { class: "hist-chart" });
    wrap.append(el("figcaption", {}, `${label} (${lo.toFixed(0)} to ${hi.toFixed(0)})`), box, legend);
    return wrap;
  }

  function stateTable(segments) {
    const table = el("table", { class: "hist-states" });
    table.appendChild(el("caption", {}, "States, newest first"));
    const head = el("tr");
    for (const h of ["State", "From", "To", "How long"]) head.appendChild(el("th", { scope: "col" }, h));
    table.appendChild(head);
    for (const seg of segments.slice().reverse().slice(0, 30)) {
      const tr = el("tr", { "data-state": seg.label });
      tr.append(el("td", {}, seg.label), el("td", {}, clock(seg.start)), el("td", {}, clock(seg.end)), el("td", {}, span(seg.seconds)));
      table.appendChild(tr);
    }
    return table;
  }

  // What the view shows now; each poll asks only for what came after its end (so the work of a
  // poll does not grow with the history kept) and for one value per pixel column of a trend.
  let view = null;  // {hours, width, data}

  function columns() {
    const body = $("history-body");
    return Math.max(100, Math.min(2000, Math.round((body && body.clientWidth) || 1000)));
  }

  function joinSegments(old, add, from) {
    const out = old.map((s) => ({ ...s }));
    for (const seg of add) {
      const last = out[out.length - 1];
      if (last && last.label === seg.label && last.end >= seg.start - 1e-6) {
        last.end = Math.max(last.end, seg.end);
      } else {
        out.push({ ...seg });
      }
    }
    return out
      .filter((s) => s.end > from)
      .map((s) => {
        const start = Math.max(s.start, from);
        return { ...s, start, seconds: s.end - start };
      });
  }

  function joinPoints(old, add, from, column) {
    const first = add.length ? add[0][0] : Infinity;  // that column and later ones are computed again
    return [...(old || []).filter((p) => p[0] < first), ...add].filter((p) => p[0] >= from - column);
  }

  // How each kind of part's history is drawn and joined with a poll's news: registered by the
  // companions' view modules (``uacellHistory.register(key, {order, view(part, range), merge(old, part,
  // from, column)})``) under the key the server answers those parts by (its ``WebView.history``).
  const HISTORY = [];
  function register(key, h) {
    HISTORY.push({ key, order: 100, ...h });
    HISTORY.sort((a, b) => a.order - b.order);
  }

  function merge(old, add) {
    const from = add.end - add.hours * 3600;
    const out = { ...add, start: Math.max(old.start, from), since: null };
    for (const h of HISTORY) {
      const before = old[h.key] || [];
      out[h.key] = (add[h.key] || []).map((p) => h.merge(before.find((x) => x.name === p.name), p, from, add.column));
    }
    return out;
  }

  async function load(full) {
    const body = $("history-body");
    if (!body) return;
    const hours = Number($("history-hours").value);
    const width = columns();
    const more = full !== true && view && view.hours === hours && view.width === width;
    const query = new URLSearchParams({ hours: String(hours), width: String(width) });
    if (more) query.set("since", String(view.data.end));
    let data;
    try {
      const token = localStorage.getItem("uacell-token") || "";  // kept by app.js: the session's token
      const res = await fetch(`/api/history?${query}`, { credentials: "same-origin", headers: { "X-CSRF-Token": token } });
      data = await res.json();
      if (!res.ok) throw new Error(data.error || res.statusText);
    } catch (err) {
      body.replaceChildren(el("p", { class: "error" }, `History: ${err.message}`));
      return;
    }
    view = { hours, width, data: more && data.since !== null ? merge(view.data, data) : data };
    const shown = view.data;
    const range = { start: shown.start, end: shown.end };
    const parts = HISTORY.flatMap((h) => (shown[h.key] || []).map((p) => h.view(p, range)));
    body.replaceChildren(...parts);
    body.dataset.loaded = String(Date.now());
  }

  // The first load waits until the page's own OPC UA session is up (app.js opens it; a request of
  // ours must not be the one that opens it).
  function whenConnected(fn) {
    const conn = $("conn");
    if (!conn || conn.dataset.status === "connected") { fn(); return; }
    const obs = new MutationObserver(() => {
      if (conn.dataset.status === "connected") { obs.disconnect(); fn(); }
    });
    obs.observe(conn, { attributes: true, attributeFilter: ["data-status"] });
  }

  // What the companions' view modules use of this view.
  window.uacellHistory = { register, el, bar, axis, trend, stateTable, clock, span, pct, joinSegments, joinPoints };

  document.addEventListener("DOMContentLoaded", () => {
    if (!$("history-body")) return;
    $("history-hours").addEventListener("change", () => load(true));
    $("history-refresh").addEventListener("click", () => load(true));
    whenConnected(() => {
      load(true);
      setInterval(load, 15000);
    });
  });
})();
