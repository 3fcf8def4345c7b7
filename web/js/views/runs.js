// Run history: the list of runs with their summaries and status, paged and filterable;
// pick two to compare.

import { listRuns } from "../api.js";
import { fmt, fmtDate, fmtDuration, fmtInt, h } from "../util.js";
import { errorBox, runTitle, statusBadge, summarize, updaterName } from "./common.js";

const PAGE = 25;
const REFRESH_MS = 4000;

export function mountRuns(root, ctx) {
  const selected = new Set();
  let offset = 0;
  let status = "";
  let timer = null;
  let destroyed = false;

  const filter = h("select", { "aria-label": "Status", "data-testid": "status-filter",
    onchange: (e) => { status = e.target.value; offset = 0; load(); } },
  ...[["", "All runs"], ["active", "Active"], ["ended", "Ended"], ["failed", "Failed"]]
    .map(([v, t]) => h("option", { value: v }, t)));
  const compareBtn = h("button.btn.primary", { type: "button", disabled: true,
    "data-testid": "compare-selected",
    onclick: () => {
      const [a, b] = [...selected];
      location.hash = `#/compare/${encodeURIComponent(a)}/${encodeURIComponent(b)}`;
    } }, "Compare selected");
  const tbody = h("tbody");
  const pager = h("div.pager");
  const message = h("div");
  const table = h("table.runs", { "data-testid": "runs-table" },
    h("thead", {}, h("tr", {},
      h("th", { title: "Select two runs to compare" }, ""),
      h("th", {}, "Run"), h("th", {}, "Status"), h("th", {}, "Created"),
      h("th.num", {}, "Duration"), h("th.num", {}, "Robots"), h("th.num", {}, "Records"),
      h("th.num", {}, "Landmarks"), h("th", {}, "Updater"), h("th.num", {}, "Particles"),
      h("th.num", {}, "Final ESS"), h("th.num", {}, "ATE RMSE"))),
    tbody);
  root.append(h("section.page", { "data-testid": "runs-view" },
    h("div.page-head", {},
      h("h1", {}, "Runs"),
      h("div.page-tools", {}, filter,
        h("button.btn", { type: "button", onclick: () => load() }, "Refresh"), compareBtn)),
    h("p.hint", {}, "Open a run to watch it live or scrub through it; tick two runs to " +
      "compare them side by side."),
    message,
    h("div.table-wrap", {}, table),
    pager));

  const updateCompare = () => {
    compareBtn.disabled = selected.size !== 2;
    compareBtn.textContent = selected.size === 2 ? "Compare selected" :
      `Compare selected (${selected.size}/2)`;
  };

  function row(run) {
    const s = summarize(run);
    const box = h("input", { type: "checkbox", "aria-label": `select ${runTitle(run)}`,
      onchange: (e) => {
        if (e.target.checked) {
          selected.add(run.id);
          while (selected.size > 2) selected.delete(selected.values().next().value);
          for (const other of tbody.querySelectorAll("input[type=checkbox]")) {
            other.checked = selected.has(other.closest("tr").dataset.runId);
          }
        } else selected.delete(run.id);
        updateCompare();
      } });
    box.checked = selected.has(run.id);
    const dur = s.duration_s;
    return h("tr", { "data-testid": "run-row", "data-run-id": run.id, "data-status": run.status },
      h("td", {}, box),
      h("td", {}, h("a.run-link", { href: `#/run/${encodeURIComponent(run.id)}` }, runTitle(run)),
        h("div.sub", {}, run.id.slice(0, 8))),
      h("td", {}, statusBadge(run.status)),
      h("td", {}, fmtDate(run.created_at)),
      h("td.num", {}, fmtDuration(dur)),
      h("td.num", {}, fmtInt(s.robots)),
      h("td.num", {}, fmtInt(s.records)),
      h("td.num", {}, s.landmarks === null ? "–" : fmtInt(s.landmarks)),
      h("td", {}, updaterName(s.updater)),
      h("td.num", {}, fmtInt(s.particles)),
      h("td.num", {}, fmt(s.final_ess, 1)),
      h("td.num", {}, s.ate_rmse === null ? "–" : `${fmt(s.ate_rmse, 3)} m`));
  }

  async function load() {
    clearTimeout(timer);
    try {
      const { runs, total } = await listRuns({ status, limit: PAGE, offset });
      if (destroyed) return;
      message.replaceChildren();
      tbody.replaceChildren(...runs.map(row));
      if (!runs.length) {
        tbody.append(h("tr", {}, h("td.empty", { colspan: 12 },
          status ? `No ${status} runs.` :
            "No runs yet. Start one with `fleetslam demo` or `fleetslam replay LOG --server URL`.")));
      }
      const prev = h("button.btn", { type: "button", disabled: offset === 0,
        onclick: () => { offset = Math.max(0, offset - PAGE); load(); } }, "← Newer");
      const next = h("button.btn", { type: "button", disabled: offset + runs.length >= total,
        onclick: () => { offset += PAGE; load(); } }, "Older →");
      pager.replaceChildren(prev,
        h("span", {}, total ? `${offset + 1}–${offset + runs.length} of ${total}` : ""), next);
      ctx.report({ view: "runs", runs: runs.length, total, ready: 1 });
      updateCompare();
    } catch (e) {
      if (destroyed) return;
      message.replaceChildren(errorBox(`Cannot list runs: ${e.message}`));
    }
    // Active runs change as they go: keep the list fresh while it is shown.
    if (!destroyed) timer = setTimeout(load, REFRESH_MS);
  }

  load();
  return {
    destroy() {
      destroyed = true;
      clearTimeout(timer);
    },
  };
}
