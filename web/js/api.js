// The server's HTTP API, as the dashboard uses it. Optional endpoints (history, truth,
// evaluation, ...) answer null when the server does not have them (404, 405) or the run has
// no such data, so that every view degrades to what is available.

export class HttpError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

// A server whose reads need a token is opened as `/?access_token=TOKEN`: the token is kept
// for this tab (sessionStorage), removed from the address bar, and sent with every request.
const TOKEN_KEY = "fleetslam.access_token";
function readToken() {
  try {
    const url = new URL(location.href);
    const t = url.searchParams.get("access_token");
    if (t) {
      sessionStorage.setItem(TOKEN_KEY, t);
      url.searchParams.delete("access_token");
      history.replaceState(null, "", url.pathname + url.search + url.hash);
    }
    return sessionStorage.getItem(TOKEN_KEY);
  } catch (_) {
    return null;
  }
}
const accessToken = readToken();

async function getJson(path, { optional = false } = {}) {
  let resp;
  const headers = { Accept: "application/json" };
  if (accessToken) headers.Authorization = `Bearer ${accessToken}`;
  try {
    resp = await fetch(path, { headers, cache: "no-store" });
  } catch (e) {
    throw new HttpError(0, `the server cannot be reached (${e.message})`);
  }
  if (optional && (resp.status === 404 || resp.status === 405 || resp.status === 409)) {
    return null;
  }
  if (!resp.ok) {
    let message = `${resp.status} ${resp.statusText}`;
    try {
      const body = await resp.json();
      if (body && body.message) message = body.message;
    } catch (_) {
      // not JSON: keep the status line
    }
    throw new HttpError(resp.status, message);
  }
  return resp.json();
}

const enc = encodeURIComponent;

/** `{runs: [...], total}`; `total` falls back to the page's length on older servers. */
export async function listRuns({ status, limit = 100, offset = 0 } = {}) {
  const q = new URLSearchParams({ limit: String(limit), offset: String(offset) });
  if (status) q.set("status", status);
  const v = await getJson(`/v1/runs?${q}`);
  return { runs: v.runs || [], total: v.total ?? (v.runs || []).length };
}

/** One run (its row: config, status, times, summary). */
export async function getRun(id) {
  const v = await getJson(`/v1/runs/${enc(id)}`);
  return v.run || v;
}

/** The run's state now (active) or its final state (ended); at data time `t` when given. */
export function getState(id, t) {
  const q = t === undefined || t === null ? "" : `?t=${enc(String(t))}`;
  return getJson(`/v1/runs/${enc(id)}/state${q}`, { optional: true });
}

export const getTimeline = (id) => getJson(`/v1/runs/${enc(id)}/timeline`, { optional: true });
/** Each robot's mean pose after every record; only the points after data time `since`. */
export function getTrajectories(id, since) {
  const q = since === undefined || since === null ? "" : `?since=${enc(String(since))}`;
  return getJson(`/v1/runs/${enc(id)}/trajectories${q}`, { optional: true });
}
/** The filter after every record (`[t, ess, step_ms, landmarks]`), thinned to `maxPoints`. */
export const getSeries = (id, maxPoints) =>
  getJson(`/v1/runs/${enc(id)}/series?max_points=${enc(String(maxPoints))}`, { optional: true });
export const getTruth = (id) => getJson(`/v1/runs/${enc(id)}/truth`, { optional: true });
export const getEvaluation = (id) =>
  getJson(`/v1/runs/${enc(id)}/evaluation`, { optional: true });

/**
 * The websocket URL of a run's live stream, with compact states (only the landmarks that
 * changed since the previous state; see `LiveSocket`).
 */
export function liveUrl(id) {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const q = new URLSearchParams({ landmarks: "delta" });
  if (accessToken) q.set("access_token", accessToken);
  return `${proto}//${location.host}/v1/runs/${enc(id)}/live?${q}`;
}

/**
 * A run's final state from its stored summary, for servers whose summary is the whole final
 * state (it has `landmarks` and `robots` arrays).
 */
export function stateFromSummary(run) {
  const s = run && run.summary;
  if (s && Array.isArray(s.landmarks) && Array.isArray(s.robots)) return s;
  return null;
}
