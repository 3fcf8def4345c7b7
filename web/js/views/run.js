// One run. Active: the live map over the websocket, per-robot status, ESS and step-time
// charts and the event list. Ended: its final map with trajectories, ground truth and error
// figures when the run has them, and a timeline to scrub through it (the state at the
// chosen data time).

import * as api from "../api.js";
import { LineChart } from "../chart.js";
import { LiveSocket } from "../live.js";
import { MapView } from "../mapview.js";
import { byId, fmt, fmtInt, fmtMs, h, robotColors } from "../util.js";
import {
  cutAt, errorBox, poseAt, poseOf, runTitle, statusBadge, summarize, trajRange, updaterName,
} from "./common.js";

/** A robot that posted nothing for this long is shown as silent [ms]. */
const SILENT_AFTER_MS = 3000;
/** Window of the client-side records-per-second figure [ms]. */
const RATE_WINDOW_MS = 3000;
/** How often a live view refetches the trajectories [ms]. */
const TRAJECTORY_REFRESH_MS = 3000;
/** Events kept in the list. */
const MAX_EVENTS = 200;
/** Points of the filter's series fetched to fill the charts of a run opened mid-way. */
const SERIES_POINTS = 3000;
/** Buckets the charts draw that series in (the ESS at each one's end, its median step). */
const SERIES_BUCKETS = 300;
const ESS_COLOR = "#0072b2";
const STEP_COLOR = "#d55e00";

/**
 * The series `[[t, ess, step_ms, landmarks], ...]` in at most `n` buckets of consecutive
 * points, as `[t, ess, step_ms]`: the time and ESS of a bucket's last point and the median
 * step time of its points (what a live state reports over its interval).
 */
export function bucketSeries(points, n) {
  const size = Math.max(1, Math.ceil(points.length / n));
  const out = [];
  for (let i = 0; i < points.length; i += size) {
    const b = points.slice(i, i + size);
    const steps = b.map((p) => p[2]).sort((x, y) => x - y);
    const last = b[b.length - 1];
    out.push([last[0], last[1], steps[Math.floor(steps.length / 2)]]);
  }
  return out;
}

export function mountRun(root, id, ctx) {
  let destroyed = false;
  let socket = null;
  let cleanup = [];
  const view = {
    run: null,
    state: null,
    poseMode: "best",
    trajectories: {}, // id -> [[t,x,y,theta]] shown (cut at the chosen time when scrubbing)
    liveTraj: { best: {}, mean: {} },
    truth: null,
    evaluation: null,
    colors: {},
    t0: null, // data time of the run's start, for charts and labels
    backfilled: false, // the charts hold the run's history from before the page opened
    trajLast: {}, // id -> time of the last trajectory point fetched from the server
    robotSeen: {}, // id -> {records, changedAt, samples: [[wall, records]]}
  };

  // --- skeleton ---------------------------------------------------------------------------
  const title = h("h1", {}, "Run");
  const badge = h("span");
  const meta = h("div.run-meta");
  const banner = h("div.banner", { hidden: true, "data-testid": "ws-banner", role: "status" });
  const note = h("div.note", { hidden: true });
  const mapHost = h("div.map-host");
  const poseBest = h("button.seg", { type: "button", "aria-pressed": "true",
    "data-testid": "pose-best", onclick: () => setPoseMode("best") }, "Best particle");
  const poseMean = h("button.seg", { type: "button", "aria-pressed": "false",
    "data-testid": "pose-mean", onclick: () => setPoseMode("mean") }, "Weighted mean");
  const toggle = (key, label, on = true) => {
    const box = h("input", { type: "checkbox", checked: on, "data-testid": `show-${key}`,
      onchange: (e) => map.setShow(key, e.target.checked) });
    return h("label.check", {}, box, label);
  };
  const truthToggle = toggle("truth", "Ground truth");
  truthToggle.hidden = true;
  const toolbar = h("div.map-toolbar", {},
    h("div.segmented", { role: "group", "aria-label": "Robot pose" }, poseBest, poseMean),
    toggle("particles", "Particles"), toggle("ellipses", "2σ ellipses"),
    toggle("trajectories", "Trajectories"), toggle("ids", "Ids"), truthToggle);
  const robotsBody = h("tbody");
  const ateHead = h("th.num", { hidden: true }, "ATE");
  const robotsTable = h("table.robots", { "data-testid": "robots-table" },
    h("thead", {}, h("tr", {}, h("th", {}, "Robot"), h("th", {}, "Mode"),
      h("th.num", { title: "last sequence number acknowledged" }, "Seq"),
      h("th.num.live-only", { title: "how far the filter is behind the robot [s]" }, "Lag s"),
      h("th.num", { title: "records acknowledged" }, "Records"),
      h("th.num.live-only", { title: "records per second" }, "Rec/s"),
      h("th.num.live-only", { title: "records waiting in the merge for the other robots" }, "Queue"),
      ateHead)),
    robotsBody);
  const figures = h("div.figures", { "data-testid": "run-figures" });
  const linkLegend = h("div.link-legend", {}, h("span.link.ok"), "posting ",
    h("span.link.warn"), "silent for 3 s");
  const errorsSection = h("section.panel", { hidden: true, "data-testid": "errors" },
    h("h2", {}, "Error against ground truth"), h("div.errors-body"));
  const eventsList = h("ol.events", { "data-testid": "events" });
  const eventsSection = h("section.panel", {}, h("h2", {}, "Events"), eventsList);
  const chartsHost = h("div.charts");
  const chartsTitle = h("h2", {}, "Over time");
  const side = h("aside.side", {},
    h("section.panel", {}, h("h2", {}, "Filter"), figures),
    h("section.panel", {}, h("h2", {}, "Robots"), h("div.table-wrap", {}, robotsTable),
      linkLegend),
    errorsSection,
    h("section.panel", {}, chartsTitle, chartsHost),
    eventsSection);
  const timeline = h("div.timeline", { hidden: true, "data-testid": "timeline-bar" });
  const body = h("div.run-body", {}, h("div.map-pane", {}, toolbar, mapHost, note), side);
  const page = h("section.run-page", { "data-testid": "run-view" },
    h("div.run-head", {},
      h("div.run-title", {}, title, badge),
      meta,
      h("div.run-links", {},
        h("a.btn", { href: `#/compare/${encodeURIComponent(id)}` }, "Compare with…"),
        h("a.btn", { href: "#/runs" }, "All runs"))),
    banner, body, timeline);
  root.append(page);
  const map = new MapView(mapHost);
  const essChart = new LineChart(chartsHost, { title: "Effective sample size", testid: "ess-chart" });
  const stepChart = new LineChart(chartsHost, { title: "Step time [ms]", testid: "step-chart" });
  ctx.report({ view: "run", run: id });

  function setPoseMode(mode) {
    view.poseMode = mode;
    map.poseMode = mode;
    poseBest.setAttribute("aria-pressed", String(mode === "best"));
    poseMean.setAttribute("aria-pressed", String(mode === "mean"));
    if (socket) view.trajectories = view.liveTraj[mode];
    draw();
  }

  // --- drawing ----------------------------------------------------------------------------
  function colorsFor(state) {
    const ids = [
      ...(state ? state.robots.map((r) => r.id) : []),
      ...Object.keys(view.trajectories),
      ...Object.keys(view.truth?.robots || {}),
    ];
    view.colors = robotColors(ids);
    return view.colors;
  }

  /**
   * Draws `view.state` (or, scrubbing without a state at that time, the final map with
   * poses interpolated at `tPose`) and reports the counts.
   */
  function draw(tPose) {
    const s = view.state;
    if (!s) return;
    const colors = colorsFor(s);
    const robots = s.robots.map((r) => ({
      id: r.id,
      mode: r.mode,
      pose: tPose !== undefined ? poseAt(view.trajectories[r.id], tPose) || poseOf(r, view.poseMode)
        : poseOf(r, view.poseMode),
    }));
    let truth = view.truth;
    if (truth && view.tCut !== undefined) {
      truth = { ...truth, robots: Object.fromEntries(Object.entries(truth.robots || {})
        .map(([k, tr]) => [k, cutAt(tr, view.tCut)])) };
    }
    const shownTraj = view.tCut !== undefined
      ? Object.fromEntries(Object.entries(view.trajectories).map(([k, tr]) => [k, cutAt(tr, view.tCut)]))
      : view.trajectories;
    map.setData({
      landmarks: s.landmarks || [],
      robots,
      trajectories: shownTraj,
      particles: tPose !== undefined ? {} : s.particle_sample || {},
      truth,
      colors,
    });
    renderFigures(s);
    renderRobots(s);
    ctx.report({
      landmarks: (s.landmarks || []).length,
      robots: s.robots.length,
      applied: s.applied,
      time: view.tCut ?? s.t ?? "",
      status: s.status,
    });
  }

  function renderFigures(s) {
    const rel = s.t !== null && s.t !== undefined && view.t0 !== null ? s.t - view.t0 : null;
    ctx.report({ elapsed: rel ?? "" });
    const item = (label, value, testid) =>
      h("div.figure", { "data-testid": testid }, h("div.fig-label", {}, label),
        h("div.fig-value", {}, value));
    figures.replaceChildren(
      item("Data time", rel === null ? "–" : `${fmt(rel, 1)} s`, "fig-time"),
      item("Applied", fmtInt(s.applied), "fig-applied"),
      item("Landmarks", fmtInt((s.landmarks || []).length), "fig-landmarks"),
      item("ESS", `${fmt(s.ess, 0)} / ${fmtInt(s.particles)}`, "fig-ess"),
      item("Resamples", fmtInt(s.resamples), "fig-resamples"),
      item(stepLabel(s), fmtMs(stepOf(s)), "fig-step"));
  }

  /**
   * The step time to show: the state's (median over its interval), else the last one seen
   * live, else a stored run's median (its summary).
   */
  function stepOf(s) {
    if (s.step_ms > 0) {
      view.lastStep = s.step_ms;
      return s.step_ms;
    }
    if (socket) return view.lastStep ?? null;
    return view.run?.summary?.step_ms_p50 ?? null;
  }

  function stepLabel(s) {
    return s.step_ms > 0 || socket ? "Step (median)" : "Step (run median)";
  }

  function robotRate(r) {
    const now = performance.now();
    let seen = view.robotSeen[r.id];
    if (!seen) {
      seen = view.robotSeen[r.id] = { records: r.records, changedAt: now, samples: [] };
    }
    if (r.records !== seen.records) {
      seen.records = r.records;
      seen.changedAt = now;
    }
    seen.samples.push([now, r.records]);
    while (seen.samples.length > 2 && now - seen.samples[0][0] > RATE_WINDOW_MS) seen.samples.shift();
    const [w0, n0] = seen.samples[0];
    const rate = r.records_per_s ?? (now - w0 > 200 ? ((r.records - n0) * 1000) / (now - w0) : null);
    const connected = typeof r.connected === "boolean" ? r.connected
      : now - seen.changedAt < SILENT_AFTER_MS;
    return { rate, connected };
  }

  function renderRobots(s) {
    const live = !!socket;
    robotsTable.classList.toggle("history", !live);
    linkLegend.hidden = !live;
    const ate = view.ateByRobot || {};
    ateHead.hidden = !Object.keys(ate).length;
    const rows = [...s.robots].sort((a, b) => byId(a.id, b.id)).map((r) => {
      const { rate, connected } = live ? robotRate(r) : { rate: null, connected: null };
      const linkText = connected ? "connected" : "silent (nothing posted for 3 s)";
      const link = live ? h(`span.link.${connected ? "ok" : "warn"}`,
        { title: linkText, "aria-label": linkText, "data-link": connected ? "connected" : "silent" })
        : null;
      return h("tr", { "data-robot": r.id },
        h("td", {}, h("span.swatch", { style: { background: view.colors[r.id] } }), r.id, link),
        h("td", {}, h(`span.mode.mode-${r.mode}`, {}, r.mode.replace("_", " "))),
        h("td.num", {}, r.last_seq ?? "–"),
        h("td.num.live-only", {}, fmt(r.lag_s, 2)),
        h("td.num", {}, fmtInt(r.records)),
        h("td.num.live-only", {}, rate === null ? "–" : fmt(rate, 1)),
        h("td.num.live-only", {}, fmtInt(r.queue_depth)),
        h("td.num", { hidden: ateHead.hidden }, ate[r.id] === undefined ? "–" : `${fmt(ate[r.id], 3)} m`));
    });
    robotsBody.replaceChildren(...rows);
  }

  function pushCharts(s, { label = true } = {}) {
    if (s.t === null || s.t === undefined) return;
    if (view.t0 === null) view.t0 = s.t_start ?? s.t;
    const x = s.t - view.t0;
    essChart.push("ess", ESS_COLOR, x, s.ess);
    if (label) essChart.setValue(`${fmt(s.ess, 0)} / ${fmtInt(s.particles)}`);
    // A state with no step in its interval (idle, or a stored final state) has step_ms 0.
    if (s.step_ms > 0) {
      stepChart.push("step", STEP_COLOR, x, s.step_ms);
      if (label) stepChart.setValue(fmtMs(s.step_ms));
    }
    reportCharts();
  }

  function reportCharts() {
    const pts = essChart.series.get("ess")?.points || [];
    ctx.report({ chartPoints: pts.length, chartFrom: pts.length ? pts[0][0] : "" });
  }

  /**
   * Fills the charts with the filter's series from the server (every record, the run's
   * history before the page opened included); says whether the server had one.
   */
  async function backfillCharts() {
    const series = await api.getSeries(id, SERIES_POINTS).catch(() => null);
    const pts = series?.points || [];
    if (destroyed || !pts.length) return false;
    if (view.t0 === null) view.t0 = pts[0][0];
    for (const [t, ess, step] of bucketSeries(pts, SERIES_BUCKETS)) {
      essChart.push("ess", ESS_COLOR, t - view.t0, ess);
      if (step > 0) stepChart.push("step", STEP_COLOR, t - view.t0, step);
    }
    reportCharts();
    ctx.report({ backfilled: 1 });
    return true;
  }

  /**
   * Fills a stored run's charts with its states at evenly spaced times (the server replays
   * from its snapshots), one request at a time, in the background.
   */
  async function sampleHistory([ta, tb]) {
    const n = 24;
    for (let i = 1; i < n; i++) {
      const t = ta + (i / n) * (tb - ta);
      const s = await api.getState(id, t).catch(() => null);
      if (destroyed || !s || (s.t !== null && s.t !== undefined && s.t > t + 1e-6)) break;
      pushCharts(s, { label: false });
    }
  }

  function addEvent(ev) {
    const kind = ev.event || ev.type || "event";
    const text = {
      robot_joined: () => `Robot ${ev.robot} joined (${(ev.mode || "").replace("_", " ")})`,
      resampled: () => `Resampled (ESS ${fmt(ev.ess, 0)})`,
      landmark_added: () => `${ev.count} landmark${ev.count === 1 ? "" : "s"} added`,
      landmark_removed: () => `${ev.count} landmark${ev.count === 1 ? "" : "s"} removed`,
      run_ended: () => "Run ended",
      lagged: () => `Missed ${ev.missed_events} events (slow connection); state refreshed`,
      connection: () => ev.text,
    }[kind];
    const label = text ? text() : `${kind.replace(/_/g, " ")} ${JSON.stringify(
      Object.fromEntries(Object.entries(ev).filter(([k]) => k !== "event")))}`;
    const first = eventsList.firstElementChild;
    const time = new Date().toLocaleTimeString([], { hour12: false });
    // Resampling can happen every few steps: fold repeats into one line.
    if (first && first.dataset.kind === kind && kind !== "connection" && kind !== "robot_joined") {
      const n = Number(first.dataset.count) + 1;
      first.dataset.count = String(n);
      first.querySelector(".ev-text").textContent = `${label} ×${n}`;
      first.querySelector(".ev-time").textContent = time;
      return;
    }
    const li = h("li", { "data-kind": kind, "data-count": "1" },
      h("span.ev-time", {}, time), h(`span.ev-dot.ev-${kind}`), h("span.ev-text", {}, label),
      ev.applied !== undefined ? h("span.ev-at", {}, `#${ev.applied}`) : null);
    eventsList.prepend(li);
    while (eventsList.children.length > MAX_EVENTS) eventsList.lastElementChild.remove();
  }

  function renderErrors() {
    const ev = view.evaluation;
    const box = errorsSection.querySelector(".errors-body");
    view.ateByRobot = {};
    if (ev && ev.robots) {
      for (const [rid, v] of Object.entries(ev.robots)) view.ateByRobot[rid] = v.ate_rmse;
    }
    const items = [];
    if (ev && ev.team) {
      items.push(h("div.figure", { "data-testid": "team-ate" }, h("div.fig-label", {}, "Team ATE RMSE"),
        h("div.fig-value", {}, `${fmt(ev.team.ate_rmse, 3)} m`)));
      if (ev.team.landmark_rmse !== undefined && ev.team.landmark_rmse !== null) {
        items.push(h("div.figure", {}, h("div.fig-label", {}, "Landmark RMSE"),
          h("div.fig-value", {}, `${fmt(ev.team.landmark_rmse, 3)} m`)));
      }
    } else if (view.truth && Object.keys(view.trajectories).length) {
      // No stored evaluation: position RMSE against truth at the estimate's times, unaligned.
      let sum = 0, n = 0;
      for (const [rid, tr] of Object.entries(view.trajectories)) {
        const truth = view.truth.robots?.[rid];
        if (!truth || !truth.length) continue;
        let rs = 0, rn = 0;
        for (const p of tr) {
          const q = poseAt(truth, p[0]);
          if (!q) continue;
          rs += (p[1] - q.x) ** 2 + (p[2] - q.y) ** 2;
          rn++;
        }
        if (rn) view.ateByRobot[rid] = Math.sqrt(rs / rn);
        sum += rs; n += rn;
      }
      if (n) {
        items.push(h("div.figure", { "data-testid": "team-ate" },
          h("div.fig-label", {}, "Team position RMSE (unaligned, computed here)"),
          h("div.fig-value", {}, `${fmt(Math.sqrt(sum / n), 3)} m`)));
      }
    }
    box.replaceChildren(h("div.figures", {}, ...items));
    errorsSection.hidden = items.length === 0;
  }

  // --- live ---------------------------------------------------------------------------------
  function live() {
    timeline.hidden = true;
    ctx.setConnection("connecting", "Connecting…");
    let wasLost = false;
    // The server keeps each robot's mean pose after every record: the states only give a
    // pose ten times a second. Fetch it now (a page opened mid-run), then now and then the
    // points added since (those after the earliest robot's last fetched point; all of them
    // again when a robot appears that no fetch had).
    const refreshTrajectories = () => {
      const known = Object.keys(view.trajLast);
      const robots = view.state ? view.state.robots.map((r) => r.id) : [];
      const since = known.length && robots.every((r) => r in view.trajLast)
        ? Math.min(...Object.values(view.trajLast)) : null;
      return api.getTrajectories(id, since).then((tr) => {
        if (!tr || destroyed || !socket) return;
        for (const [rid, pts] of Object.entries(tr.robots || {})) {
          if (!pts.length) continue;
          const tBegin = pts[0][0];
          const tEnd = pts[pts.length - 1][0];
          view.trajLast[rid] = tEnd;
          const mean = view.liveTraj.mean[rid] || [];
          view.liveTraj.mean[rid] = mean.filter((p) => p[0] < tBegin).concat(pts,
            mean.filter((p) => p[0] > tEnd));
          const best = view.liveTraj.best[rid] || [];
          const t0 = best.length ? best[0][0] : Infinity;
          view.liveTraj.best[rid] = pts.filter((p) => p[0] < t0).concat(best);
        }
        view.trajectories = view.liveTraj[view.poseMode];
        draw();
      }).catch(() => {});
    };
    refreshTrajectories();
    view.trajTimer = setInterval(refreshTrajectories, TRAJECTORY_REFRESH_MS);
    api.getTruth(id).then((t) => {
      if (!t || destroyed) return;
      view.truth = t;
      truthToggle.hidden = false;
      draw();
    }).catch(() => {});
    socket = new LiveSocket(api.liveUrl(id), {
      onState(s) {
        view.state = s;
        for (const r of s.robots) {
          if (s.t === null || s.t === undefined) continue;
          for (const m of ["best", "mean"]) {
            const p = m === "best" ? r.best : r.mean;
            if (!p) continue;
            const tr = (view.liveTraj[m][r.id] ||= []);
            const last = tr[tr.length - 1];
            if (!last || s.t > last[0]) tr.push([s.t, p.x, p.y, p.theta]);
          }
        }
        view.trajectories = view.liveTraj[view.poseMode];
        pushCharts(s);
        // A page opened mid-way: the charts' history before it, once.
        if (!view.backfilled && s.t !== null && s.t !== undefined) {
          view.backfilled = true;
          backfillCharts();
        }
        draw();
        const fs = map.frameStats();
        ctx.report({ wsBytes: socket.bytes, wsStates: socket.states, frames: fs.frames,
          frameMs: fs.mean.toFixed(3), frameMaxMs: fs.max.toFixed(3) });
        if (s.status && s.status !== "active") toHistory();
      },
      onEvent(ev) {
        addEvent(ev);
        if (ev.event === "run_ended") toHistory();
      },
      onLagged(m) {
        addEvent({ event: "lagged", missed_events: m.missed_events });
      },
      onStatus({ state, attempt, inMs }) {
        if (state === "open") {
          ctx.setConnection("open", "● Live");
          if (wasLost) {
            addEvent({ event: "connection", text: "Live connection restored" });
            showBanner("ok", "Live connection restored.");
            setTimeout(() => { if (banner.dataset.kind === "ok") banner.hidden = true; }, 3000);
          } else banner.hidden = true;
          wasLost = false;
        } else if (state === "closed") {
          if (!wasLost && socket.everOpened) {
            addEvent({ event: "connection", text: "Live connection lost" });
          }
          wasLost = socket.everOpened || wasLost;
          const secs = Math.max(1, Math.round(inMs / 1000));
          ctx.setConnection("closed", "Reconnecting…");
          showBanner("warn", `Live connection lost. Reconnecting in ${secs} s (attempt ${attempt})…`);
        } else if (state === "reconnecting") {
          showBanner("warn", `Live connection lost. Reconnecting (attempt ${attempt})…`);
        }
      },
      async beforeReconnect() {
        // The run may have ended (its stream closes): show its history instead.
        let run;
        try {
          run = await api.getRun(id);
        } catch (e) {
          if (e.status !== 404) throw e; // unreachable server: keep trying
          showBanner("warn", "This run no longer exists on the server.");
          ctx.setConnection("ended", "Run deleted");
          return false;
        }
        if (run.status !== "active") {
          toHistory();
          return false;
        }
        return true;
      },
    }).start();
  }

  function showBanner(kind, text) {
    banner.dataset.kind = kind;
    banner.className = `banner banner-${kind}`;
    banner.textContent = text;
    banner.hidden = false;
  }

  let switching = false;
  function toHistory() {
    if (switching || destroyed) return;
    switching = true;
    if (socket) socket.stop();
    socket = null;
    clearInterval(view.trajTimer);
    // Let the server store the final state before asking for it.
    setTimeout(() => { if (!destroyed) start(); }, 300);
  }

  // --- history and scrubbing ------------------------------------------------------------
  async function history() {
    ctx.setConnection("ended", "Stored run");
    banner.hidden = true;
    const [state, tl, traj, truth, evaluation] = await Promise.all([
      api.getState(id), api.getTimeline(id), api.getTrajectories(id), api.getTruth(id),
      api.getEvaluation(id),
    ].map((p) => p.catch(() => null)));
    if (destroyed) return;
    const final = state || api.stateFromSummary(view.run);
    view.trajectories = traj?.robots || {};
    view.truth = truth;
    view.evaluation = evaluation;
    truthToggle.hidden = !truth;
    if (!final) {
      note.hidden = false;
      note.textContent = "The server has no stored state for this run.";
      ctx.report({ ready: 1, landmarks: 0, robots: 0 });
      return;
    }
    view.state = final;
    let range = null;
    if (tl && tl.t_start !== null && tl.t_end !== null && tl.t_end !== undefined) {
      range = [tl.t_start, tl.t_end];
    }
    range = range || trajRange(view.trajectories);
    if (!range && final.t !== null && final.t !== undefined) {
      const starts = (view.run.header?.robots || []).map((r) => r.t0).filter(Number.isFinite);
      range = [starts.length ? Math.min(...starts) : final.t, final.t];
    }
    view.t0 = range ? range[0] : final.t;
    // Events stream live only: a stored run shows those seen while this page watched it.
    eventsSection.hidden = eventsList.children.length === 0;
    renderErrors();
    pushCharts(final);
    draw();
    if (range && range[1] > range[0]) setupTimeline(range, final);
    // Every record's ESS and step time; a run stored before the server kept them is sampled
    // at evenly spaced times instead.
    backfillCharts().then(async (filled) => {
      if (!filled && range && range[1] > range[0]) {
        chartsTitle.textContent = "Over the run (sampled)";
        await sampleHistory(range);
      }
      if (!destroyed) ctx.report({ sampled: 1 });
    });
    ctx.report({ ready: 1 });
  }

  function setupTimeline([ta, tb], final) {
    const STEPS = 1000;
    const slider = h("input.slider", { type: "range", min: 0, max: STEPS, step: 1, value: STEPS,
      "aria-label": "Time", "data-testid": "timeline" });
    const label = h("span.time-label", { "data-testid": "time-label" });
    const play = h("button.btn.play", { type: "button", "data-testid": "play",
      "aria-label": "Play" }, "▶ Play");
    const speed = h("select", { "aria-label": "Playback speed" },
      ...[["1", "×1"], ["10", "×10"], ["50", "×50"], ["200", "×200"]]
        .map(([v, t]) => h("option", { value: v, selected: v === "10" }, t)));
    const toEnd = h("button.btn", { type: "button", title: "Final state",
      onclick: () => { stop(); slider.value = STEPS; onScrub(true); } }, "End");
    timeline.replaceChildren(play, speed, slider, label, toEnd);
    timeline.hidden = false;
    const span = tb - ta;
    const tOf = () => ta + (Number(slider.value) / STEPS) * span;
    const setLabel = (t) => {
      label.textContent = `t = ${fmt(t - ta, 1)} s / ${fmt(span, 1)} s`;
    };
    setLabel(final.t ?? tb);
    let seq = 0;
    let fetchTimer = null;
    let playing = null;
    let scrubUnsupported = false;

    async function fetchAt(t, mine) {
      const s = scrubUnsupported ? null : await api.getState(id, t).catch(() => null);
      if (mine !== seq || destroyed) return;
      // A server without states at a chosen time answers with the final state (or nothing):
      // then show the final map with the poses interpolated along the trajectories.
      const valid = s && (s.t === null || s.t === undefined || s.t <= t + 1e-6);
      if (s && !valid) scrubUnsupported = true;
      if (valid) {
        view.state = s;
        note.hidden = true;
        pushCharts(s);
        draw();
      } else {
        view.state = final;
        note.hidden = false;
        note.textContent = "Map as at the end of the run; robots along their trajectories " +
          "(this server cannot give the state at a chosen time).";
        draw(t);
      }
      ctx.report({ time: t, scrubbed: mine });
    }

    function onScrub(now) {
      const t = tOf();
      const atEnd = Number(slider.value) >= STEPS;
      view.tCut = atEnd ? undefined : t;
      setLabel(t);
      ctx.report({ time: t });
      const mine = ++seq;
      clearTimeout(fetchTimer);
      if (atEnd) {
        view.state = final;
        note.hidden = true;
        draw();
        ctx.report({ time: final.t ?? t, scrubbed: mine });
        return Promise.resolve();
      }
      // Move the robots along their trajectories at once; the map at t follows.
      if (Object.keys(view.trajectories).length) draw(t);
      return new Promise((resolve) => {
        fetchTimer = setTimeout(() => fetchAt(t, mine).then(resolve), now ? 0 : 120);
      });
    }

    function stop() {
      if (playing) clearTimeout(playing);
      playing = null;
      play.textContent = "▶ Play";
      play.setAttribute("aria-label", "Play");
    }

    async function tick() {
      const wallStep = 250; // ms between frames
      const dt = (Number(speed.value) * wallStep) / 1000;
      let v = Number(slider.value) + Math.max(1, Math.round((dt / span) * STEPS));
      if (v >= STEPS) v = STEPS;
      slider.value = v;
      const started = performance.now();
      await onScrub(true);
      if (!playing) return;
      if (v >= STEPS) { stop(); return; }
      playing = setTimeout(tick, Math.max(0, wallStep - (performance.now() - started)));
    }

    play.addEventListener("click", () => {
      if (playing) { stop(); return; }
      if (Number(slider.value) >= STEPS) {
        slider.value = 0;
        essChart.clear();
        stepChart.clear();
      }
      play.textContent = "❚❚ Pause";
      play.setAttribute("aria-label", "Pause");
      playing = setTimeout(tick, 0);
    });
    slider.addEventListener("input", () => { stop(); onScrub(false); });
    cleanup.push(() => { stop(); clearTimeout(fetchTimer); });
  }

  // --- start ------------------------------------------------------------------------------
  async function start() {
    switching = false;
    try {
      view.run = await api.getRun(id);
    } catch (e) {
      if (destroyed) return;
      page.replaceChildren(errorBox(e.status === 404 ? `No run ${id}.` : `Cannot load run ${id}: ${e.message}`),
        h("p", {}, h("a", { href: "#/runs" }, "Back to the runs")));
      ctx.report({ ready: 1, error: e.message });
      return;
    }
    if (destroyed) return;
    const run = view.run;
    const s = summarize(run);
    title.textContent = runTitle(run);
    document.title = `${runTitle(run)} · fleetslam`;
    badge.replaceChildren(statusBadge(run.status));
    meta.replaceChildren(
      h("span", { title: run.id }, `id ${run.id.slice(0, 8)}`),
      h("span", {}, `${fmtInt(s.particles)} particles`),
      h("span", {}, `updater ${updaterName(s.updater)}`),
      s.version ? h("span", {}, `FastSLAM ${s.version}`) : null,
      s.association ? h("span", {}, `association ${s.association}`) : null);
    ctx.report({ runStatus: run.status });
    if (run.status === "active") live();
    else await history();
  }

  start().catch((e) => {
    if (!destroyed) page.append(errorBox(`Error: ${e.message}`));
  });

  return {
    destroy() {
      destroyed = true;
      if (socket) socket.stop();
      clearInterval(view.trajTimer);
      for (const f of cleanup) f();
      map.destroy();
      essChart.destroy();
      stepChart.destroy();
    },
  };
}
