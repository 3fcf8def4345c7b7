// What the views share: a run's summary figures whatever the server's summary shape, and
// small pieces of markup.

import { h } from "../util.js";

/**
 * The figures of a run's list row: `{robots, records, landmarks, duration_s, updater,
 * particles, final_ess, ate_rmse, step_ms}`. Reads the summary the server stores when a run
 * ends (either the documented summary object, or a whole final state on older servers),
 * then the row's own counts and configuration.
 */
export function summarize(run) {
  const s = run.summary || {};
  const cfg = run.config || {};
  const count = (v) => (Array.isArray(v) ? v.length : typeof v === "number" ? v : null);
  let duration = s.duration_s ?? null;
  if (duration === null && run.ended_at && run.created_at) {
    duration = (run.ended_at - run.created_at) / 1000;
  }
  return {
    robots: count(s.robots) ?? run.robots ?? null,
    records: s.records ?? run.records ?? null,
    landmarks: count(s.landmarks),
    duration_s: duration,
    updater: s.updater ?? cfg.updater ?? null,
    particles: s.particles ?? cfg.particles ?? null,
    version: cfg.version ?? cfg.fastslam_version ?? null,
    association: cfg.association ?? null,
    final_ess: s.final_ess ?? s.ess ?? null,
    ate_rmse: s.ate_rmse ?? s.evaluation?.team?.ate_rmse ?? null,
    step_ms: s.step_ms_p50 ?? s.step_ms ?? null,
  };
}

/** Displayed name of the updater in a configuration (a string, or an object naming a model). */
export function updaterName(u) {
  if (u === null || u === undefined) return "–";
  if (typeof u === "string") return u;
  if (typeof u === "object") return u.model || u.id || u.kind || Object.keys(u)[0] || "custom";
  return String(u);
}

export function statusBadge(status) {
  return h(`span.badge.badge-${status || "unknown"}`, { "data-testid": "run-status" },
    status || "unknown");
}

export function runTitle(run) {
  return run.name || `run ${run.id.slice(0, 8)}`;
}

/** A robot's pose by the chosen estimate ("best" or "mean"), falling back to the other. */
export function poseOf(r, mode) {
  return (mode === "mean" ? r.mean || r.best : r.best || r.mean) || null;
}

/** Interpolates a trajectory `[[t,x,y,theta]]` (sorted by t) at time t. */
export function poseAt(tr, t) {
  if (!tr || !tr.length) return null;
  if (t <= tr[0][0]) return { x: tr[0][1], y: tr[0][2], theta: tr[0][3] };
  const last = tr[tr.length - 1];
  if (t >= last[0]) return { x: last[1], y: last[2], theta: last[3] };
  let lo = 0, hi = tr.length - 1;
  while (hi - lo > 1) {
    const mid = (lo + hi) >> 1;
    if (tr[mid][0] <= t) lo = mid; else hi = mid;
  }
  const a = tr[lo], b = tr[hi];
  const f = (t - a[0]) / (b[0] - a[0] || 1);
  let dth = b[3] - a[3];
  dth = Math.atan2(Math.sin(dth), Math.cos(dth));
  return { x: a[1] + f * (b[1] - a[1]), y: a[2] + f * (b[2] - a[2]), theta: a[3] + f * dth };
}

/** The part of a trajectory up to time t. */
export function cutAt(tr, t) {
  if (!tr || t === null || t === undefined) return tr || [];
  let n = tr.length;
  while (n > 0 && tr[n - 1][0] > t) n--;
  return tr.slice(0, n);
}

/** Time range of trajectories: [t0, t1] or null. */
export function trajRange(robots) {
  let t0 = Infinity, t1 = -Infinity;
  for (const tr of Object.values(robots || {})) {
    if (tr.length) {
      t0 = Math.min(t0, tr[0][0]);
      t1 = Math.max(t1, tr[tr.length - 1][0]);
    }
  }
  return t0 <= t1 ? [t0, t1] : null;
}

export function errorBox(message) {
  return h("div.error-box", { role: "alert", "data-testid": "error" }, message);
}
