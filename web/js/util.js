// Small helpers shared by the views: colours, number formats, DOM building.

/** Robot colours (Okabe-Ito, colour-blind safe), then a few more. */
export const PALETTE = [
  "#0072b2", "#d55e00", "#009e73", "#cc79a7", "#e69f00",
  "#56b4e9", "#8c564b", "#7f7f7f", "#bcbd22", "#17becf",
];

/** A stable colour per robot id, by its order in `ids` (sorted). */
export function robotColors(ids) {
  const sorted = [...new Set(ids)].sort((a, b) =>
    a.localeCompare(b, undefined, { numeric: true }));
  const out = {};
  sorted.forEach((id, i) => { out[id] = PALETTE[i % PALETTE.length]; });
  return out;
}

export function fmt(v, digits = 2) {
  if (v === null || v === undefined || Number.isNaN(v)) return "–";
  if (typeof v !== "number") return String(v);
  if (!Number.isFinite(v)) return v > 0 ? "∞" : "-∞";
  return v.toFixed(digits);
}

/** Milliseconds with three significant digits ("0.0213 ms", "2.13 ms", "213 ms"). */
export function fmtMs(v) {
  if (v === null || v === undefined || !Number.isFinite(v)) return "–";
  if (v === 0) return "0 ms";
  return `${v >= 100 ? v.toFixed(0) : v.toPrecision(3)} ms`;
}

export function fmtInt(v) {
  if (v === null || v === undefined) return "–";
  return Number(v).toLocaleString("en-US");
}

export function fmtDuration(s) {
  if (s === null || s === undefined || !Number.isFinite(s)) return "–";
  if (s < 60) return `${s.toFixed(1)} s`;
  const m = Math.floor(s / 60);
  const r = Math.round(s - 60 * m);
  if (m < 60) return `${m} min ${r} s`;
  return `${Math.floor(m / 60)} h ${m % 60} min`;
}

export function fmtDate(ms) {
  if (!ms) return "–";
  const d = new Date(ms);
  const pad = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
    `${pad(d.getHours())}:${pad(d.getMinutes())}`;
}

/**
 * Builds an element: `h("div.a.b", {attrs}, ...children)`. Attributes starting with "on"
 * are listeners; `dataset` and `style` take objects; children may be strings or nodes.
 */
export function h(tag, attrs = {}, ...children) {
  const [name, ...classes] = tag.split(".");
  const el = document.createElement(name || "div");
  if (classes.length) el.className = classes.join(" ");
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith("on") && typeof v === "function") el.addEventListener(k.slice(2), v);
    else if (k === "dataset") Object.assign(el.dataset, v);
    else if (k === "style" && typeof v === "object") Object.assign(el.style, v);
    else if (k === "class") el.className += (el.className ? " " : "") + v;
    else if (v === true) el.setAttribute(k, "");
    else el.setAttribute(k, String(v));
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

/** The short form of a run id (uuid) for tables and titles. */
export const shortId = (id) => (id && id.length > 8 ? id.slice(0, 8) : id);

/** Orders robot ids naturally ("2" before "10"). */
export const byId = (a, b) => String(a).localeCompare(String(b), undefined, { numeric: true });
