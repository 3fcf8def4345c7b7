// The dashboard's entry: hash routes to views, the connection indicator and the status
// element the browser test reads.
//
//   #/runs                 run history (default)
//   #/run/<id>             one run: live over the websocket when active, else its history
//   #/compare              pick two runs
//   #/compare/<a>/<b>      two runs side by side

import { mountRuns } from "./views/runs.js";
import { mountRun } from "./views/run.js";
import { mountCompare } from "./views/compare.js";

const view = document.getElementById("view");
const conn = document.getElementById("conn");

/**
 * A hidden element whose data attributes report what the page shows (for tests and for
 * anyone scripting the dashboard): data-view, data-run, data-landmarks, data-robots,
 * data-time, data-applied, data-ws, data-ready.
 */
const status = document.createElement("div");
status.id = "status";
status.hidden = true;
status.setAttribute("data-testid", "status");
document.body.append(status);

export function report(values) {
  for (const [k, v] of Object.entries(values)) {
    if (v === undefined || v === null) delete status.dataset[k];
    else status.dataset[k] = String(v);
  }
}

/** The header's connection indicator: `state` is none, connecting, open, closed, ended. */
export function setConnection(state, text) {
  conn.dataset.ws = state;
  conn.hidden = state === "none";
  conn.textContent = text || "";
  report({ ws: state });
}

let current = null;

function route() {
  if (current && current.destroy) current.destroy();
  current = null;
  for (const k of Object.keys(status.dataset)) delete status.dataset[k];
  setConnection("none");
  view.replaceChildren();
  document.title = "fleetslam dashboard";
  const parts = location.hash.replace(/^#\/?/, "").split("/").filter(Boolean)
    .map(decodeURIComponent);
  const [name, a, b] = parts;
  for (const link of document.querySelectorAll("[data-nav]")) {
    link.classList.toggle("active", link.dataset.nav === (name || "runs") ||
      (link.dataset.nav === "runs" && name === "run"));
  }
  const ctx = { report, setConnection };
  try {
    if (name === "run" && a) current = mountRun(view, a, ctx);
    else if (name === "compare") current = mountCompare(view, a, b, ctx);
    else current = mountRuns(view, ctx);
  } catch (e) {
    console.error(e);
  }
}

window.addEventListener("hashchange", route);
route();
