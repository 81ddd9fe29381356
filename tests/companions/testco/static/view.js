// TestCo's view in the web HMI (tests only): one card per unit with a thermometer, its temperature
// live, and the temperatures history keeps. Registered like any companion's view.
const {S, $$, el, registerView} = window.uacell;
const HIST = window.uacellHistory;

function render(t) {
  return el("section", {class: "card thermometer", id: `thermometer-${t.name}`, "data-thermometer": t.name},
    el("h2", {text: `${t.name}: thermometer`}),
    el("div", {}, "Temperature ", el("strong", {class: "t-value", text: "–"}), " °C"));
}

function update(parts) {
  for (const t of parts) {
    for (const card of $$(`section.thermometer[data-thermometer="${t.name}"]`)) {
      const v = S.values[t.temperature];
      card.querySelector(".t-value").textContent = typeof v === "number" ? v.toFixed(1) : "–";
    }
  }
}

function tree(t) {
  return el("li", {}, el("a", {href: `#thermometer-${t.name}`, text: `${t.name} (thermometer)`}));
}

registerView("thermometers", {order: 30, noun: "thermometer", tree, render, update});

function history(t) {
  const art = HIST.el("article", {class: "hist-thermometer", "data-thermometer": t.name});
  art.append(HIST.el("h3", {}, `${t.name} temperature`),
    HIST.el("p", {class: "t-history"}, t.temperatures.map(([, v]) => v.toFixed(1)).join(" ")));
  return art;
}

HIST.register("thermometers", {order: 30, view: history, merge: (_old, t) => t});
