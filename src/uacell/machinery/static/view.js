// The web HMI's view of OPC 40001-1 machines (``Companion.web_view`` of uacell.machinery): one tile
// per object Objects/Machines organizes, with its MachineryItemState and MachineryOperationMode.
// Loaded by the page as a module after app.js; draws what uacell.machinery.web_view describes.
const {S, $, $$, el, api, button, lockBox, stateLine, machineText, showResult, updateButtons, registerView} = window.uacell;

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
registerView("machines", {
  order: 0, overview: true, render: renderMachines, update: updateMachines,
});
