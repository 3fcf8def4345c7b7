// Two runs side by side (for example the same log with the EKF and with a learned updater):
// their final maps and trajectories over the ground truth, and a table of their figures
// (error, time per step, landmarks, ESS). Without two ids, a picker.

import * as api from "../api.js";
import { MapView } from "../mapview.js";
import { fmt, fmtDuration, fmtInt, h, robotColors } from "../util.js";
import { errorBox, poseOf, runTitle, statusBadge, summarize, updaterName } from "./common.js";

export function mountCompare(root, a, b, ctx) {
  if (!a || !b) return mountPicker(root, a, ctx);
  let destroyed = false;
  const maps = [];
  const table = h("table.compare", { "data-testid": "compare-table" });
  const cols = h("div.compare-cols");
  root.append(h("section.page.compare-page", { "data-testid": "compare-view" },
    h("div.page-head", {}, h("h1", {}, "Compare runs"),
      h("div.page-tools", {},
        h("a.btn", { href: `#/compare/${encodeURIComponent(b)}/${encodeURIComponent(a)}` }, "Swap"),
        h("a.btn", { href: "#/compare" }, "Pick other runs"))),
    cols,
    h("div.table-wrap", {}, table)));
  ctx.report({ view: "compare", runA: a, runB: b });

  async function loadOne(id) {
    const run = await api.getRun(id);
    const [state, traj, truth, evaluation] = await Promise.all([
      api.getState(id), api.getTrajectories(id), api.getTruth(id), api.getEvaluation(id),
    ].map((p) => p.catch(() => null)));
    return { run, state: state || api.stateFromSummary(run), traj, truth, evaluation };
  }

  Promise.all([loadOne(a), loadOne(b)]).then((runs) => {
    if (destroyed) return;
    const ids = runs.flatMap((r) => [
      ...(r.state?.robots || []).map((x) => x.id), ...Object.keys(r.traj?.robots || {})]);
    const colors = robotColors(ids);
    runs.forEach((r, i) => {
      const host = h("div.map-host");
      const col = h("div.compare-col", { "data-testid": `compare-${i ? "b" : "a"}` },
        h("div.compare-head", {},
          h("a", { href: `#/run/${encodeURIComponent(r.run.id)}` }, runTitle(r.run)), " ",
          statusBadge(r.run.status),
          h("span.sub", {}, ` ${updaterName(summarize(r.run).updater)}`)),
        host);
      cols.append(col);
      const map = new MapView(host);
      maps.push(map);
      const s = r.state;
      map.setData({
        landmarks: s?.landmarks || [],
        robots: (s?.robots || []).map((x) => ({ id: x.id, mode: x.mode, pose: poseOf(x, "best") })),
        trajectories: r.traj?.robots || {},
        particles: {},
        truth: r.truth,
        colors,
      });
    });
    renderTable(runs);
    ctx.report({
      ready: 1,
      landmarks: runs.map((r) => (r.state?.landmarks || []).length).join(","),
      robots: runs.map((r) => (r.state?.robots || []).length).join(","),
    });
  }).catch((e) => {
    if (!destroyed) cols.replaceChildren(errorBox(`Cannot load the runs: ${e.message}`));
  });

  function renderTable(runs) {
    const rows = [];
    const sums = runs.map((r) => summarize(r.run));
    // lower: true when less is better (highlighted).
    const add = (label, values, { lower, text } = {}) => {
      const nums = values.map((v) => (typeof v === "number" && Number.isFinite(v) ? v : null));
      let best = null;
      if (lower !== undefined && nums.every((v) => v !== null) && nums[0] !== nums[1]) {
        best = lower ? (nums[0] < nums[1] ? 0 : 1) : (nums[0] > nums[1] ? 0 : 1);
      }
      rows.push(h("tr", {}, h("th", {}, label), ...values.map((v, i) =>
        h(`td.num${best === i ? ".better" : ""}`, {}, text ? text(v) : v ?? "–"))));
    };
    const ev = runs.map((r) => r.evaluation);
    add("Status", runs.map((r) => r.run.status));
    add("Updater", sums.map((s) => updaterName(s.updater)));
    add("Particles", sums.map((s) => s.particles), { text: fmtInt });
    add("FastSLAM version", sums.map((s) => s.version));
    add("Robots", sums.map((s) => s.robots), { text: fmtInt });
    add("Records", sums.map((s) => s.records), { text: fmtInt });
    add("Landmarks", runs.map((r) => (r.state?.landmarks || []).length), { text: fmtInt });
    add("Duration", sums.map((s) => s.duration_s), { text: fmtDuration });
    add("Final ESS", runs.map((r) => r.state?.ess ?? null), { text: (v) => fmt(v, 1), lower: false });
    add("Time per step [ms]", sums.map((s, i) => s.step_ms ?? runs[i].state?.step_ms ?? null),
      { text: (v) => fmt(v, 3), lower: true });
    add("Team ATE RMSE [m]", ev.map((e, i) => e?.team?.ate_rmse ?? sums[i].ate_rmse),
      { text: (v) => fmt(v, 3), lower: true });
    add("Landmark RMSE [m]", ev.map((e) => e?.team?.landmark_rmse ?? null),
      { text: (v) => fmt(v, 3), lower: true });
    const robotIds = [...new Set(ev.flatMap((e) => Object.keys(e?.robots || {})))].sort();
    for (const rid of robotIds) {
      add(`ATE robot ${rid} [m]`, ev.map((e) => e?.robots?.[rid]?.ate_rmse ?? null),
        { text: (v) => fmt(v, 3), lower: true });
    }
    table.replaceChildren(
      h("thead", {}, h("tr", {}, h("th", {}, ""),
        ...runs.map((r) => h("th.num", {}, runTitle(r.run))))),
      h("tbody", {}, ...rows));
  }

  return {
    destroy() {
      destroyed = true;
      for (const m of maps) m.destroy();
    },
  };
}

function mountPicker(root, preset, ctx) {
  const selA = h("select", { "aria-label": "First run", "data-testid": "pick-a" });
  const selB = h("select", { "aria-label": "Second run", "data-testid": "pick-b" });
  const go = h("button.btn.primary", { type: "button", "data-testid": "compare-go",
    onclick: () => {
      if (selA.value && selB.value) {
        location.hash = `#/compare/${encodeURIComponent(selA.value)}/${encodeURIComponent(selB.value)}`;
      }
    } }, "Compare");
  const msg = h("div");
  root.append(h("section.page", { "data-testid": "compare-picker" },
    h("div.page-head", {}, h("h1", {}, "Compare runs")),
    h("p.hint", {}, "Pick two runs, for example the same log run with the EKF and with a " +
      "learned updater."),
    msg,
    h("div.picker", {}, selA, h("span", {}, "against"), selB, go)));
  api.listRuns({ limit: 200 }).then(({ runs }) => {
    const opts = (sel) => runs.map((r) => h("option", { value: r.id },
      `${runTitle(r)} (${r.status}, ${r.id.slice(0, 8)})`));
    selA.replaceChildren(...opts(selA));
    selB.replaceChildren(...opts(selB));
    if (preset) selA.value = preset;
    const other = runs.find((r) => r.id !== selA.value);
    if (other) selB.value = other.id;
    if (runs.length < 2) msg.replaceChildren(errorBox("Comparing needs at least two runs."));
    ctx.report({ view: "compare-picker", ready: 1 });
  }).catch((e) => msg.replaceChildren(errorBox(`Cannot list runs: ${e.message}`)));
  return { destroy() {} };
}
