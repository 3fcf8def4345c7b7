// A small line chart on canvas for time series (ESS, step time): axes with ticks, one or
// more series, a fixed number of kept points. No library: the dashboard has no build step.

import { h } from "./util.js";

function niceTicks(lo, hi, n) {
  const span = hi - lo || 1;
  const raw = span / n;
  const p = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * p).find((s) => s >= raw) || 10 * p;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(v);
  return { ticks: out, step };
}

function tickLabel(v, step) {
  if (Math.abs(v) >= 10000) return `${(v / 1000).toFixed(0)}k`;
  return step >= 1 ? v.toFixed(0) : v.toFixed(Math.min(3, Math.ceil(-Math.log10(step))));
}

export class LineChart {
  /**
   * @param {HTMLElement} host
   * @param {object} opts `{title, unit, maxPoints, yMin, testid}`
   */
  constructor(host, opts) {
    this.opts = { maxPoints: 600, yMin: 0, ...opts };
    this.series = new Map(); // name -> {color, points}
    this.canvas = h("canvas.chart-canvas");
    this.value = h("span.chart-value", {}, "–");
    this.root = h("figure.chart", { "data-testid": opts.testid || "chart" },
      h("figcaption", {}, h("span.chart-title", {}, opts.title), this.value),
      this.canvas);
    host.append(this.root);
    this.ctx = this.canvas.getContext("2d");
    this.ro = new ResizeObserver(() => this.schedule());
    this.ro.observe(this.canvas);
  }

  destroy() {
    this.ro.disconnect();
    this.root.remove();
  }

  clear() {
    this.series.clear();
    this.schedule();
  }

  /** Adds (x, y) to a series in x order; a point at the same x is replaced. */
  push(name, color, x, y) {
    if (!Number.isFinite(x) || !Number.isFinite(y)) return;
    let s = this.series.get(name);
    if (!s) {
      s = { color, points: [] };
      this.series.set(name, s);
    }
    const pts = s.points;
    let i = pts.length;
    while (i > 0 && pts[i - 1][0] > x) i--;
    if (i > 0 && Math.abs(pts[i - 1][0] - x) < 1e-9) pts[i - 1] = [x, y];
    else pts.splice(i, 0, [x, y]);
    if (pts.length > this.opts.maxPoints) pts.splice(0, pts.length - this.opts.maxPoints);
    this.schedule();
  }

  /** Replaces every series with sorted points. */
  setSeries(name, color, points) {
    this.series.set(name, { color, points: points.slice().sort((a, b) => a[0] - b[0]) });
    this.schedule();
  }

  setValue(text) {
    this.value.textContent = text;
  }

  schedule() {
    if (this.raf) return;
    this.raf = requestAnimationFrame(() => {
      this.raf = null;
      this.draw();
    });
  }

  draw() {
    const dpr = window.devicePixelRatio || 1;
    const r = this.canvas.getBoundingClientRect();
    const w = Math.max(r.width, 1), hgt = Math.max(r.height, 1);
    if (this.canvas.width !== Math.round(w * dpr) || this.canvas.height !== Math.round(hgt * dpr)) {
      this.canvas.width = Math.round(w * dpr);
      this.canvas.height = Math.round(hgt * dpr);
    }
    const ctx = this.ctx;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, hgt);
    const all = [...this.series.values()].flatMap((s) => s.points);
    ctx.font = "10px system-ui, sans-serif";
    if (!all.length) {
      ctx.fillStyle = "#94a3b8";
      ctx.textAlign = "center"; ctx.textBaseline = "middle";
      ctx.fillText("no data yet", w / 2, hgt / 2);
      return;
    }
    let x0 = Math.min(...all.map((p) => p[0])), x1 = Math.max(...all.map((p) => p[0]));
    let y0 = Math.min(this.opts.yMin ?? Infinity, ...all.map((p) => p[1]));
    let y1 = Math.max(...all.map((p) => p[1]));
    if (x1 - x0 < 1e-9) { x0 -= 1; x1 += 1; }
    if (y1 - y0 < 1e-9) y1 = y0 + 1;
    y1 += (y1 - y0) * 0.08;
    const L = 38, R = 8, T = 6, B = 18;
    const X = (x) => L + ((x - x0) / (x1 - x0)) * (w - L - R);
    const Y = (y) => T + (1 - (y - y0) / (y1 - y0)) * (hgt - T - B);
    ctx.strokeStyle = "#e5e7eb";
    ctx.fillStyle = "#6b7280";
    ctx.lineWidth = 1;
    const yt = niceTicks(y0, y1, 3);
    ctx.textAlign = "right"; ctx.textBaseline = "middle";
    for (const v of yt.ticks) {
      const y = Math.round(Y(v)) + 0.5;
      ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(w - R, y); ctx.stroke();
      ctx.fillText(tickLabel(v, yt.step), L - 4, y);
    }
    const xt = niceTicks(x0, x1, 4);
    ctx.textAlign = "center"; ctx.textBaseline = "top";
    for (const v of xt.ticks) ctx.fillText(`${tickLabel(v, xt.step)} s`, X(v), hgt - B + 4);
    for (const s of this.series.values()) {
      if (!s.points.length) continue;
      ctx.strokeStyle = s.color;
      ctx.lineWidth = 1.6;
      ctx.beginPath();
      s.points.forEach((p, i) => (i ? ctx.lineTo(X(p[0]), Y(p[1])) : ctx.moveTo(X(p[0]), Y(p[1]))));
      ctx.stroke();
      if (s.points.length === 1) {
        ctx.fillStyle = s.color;
        ctx.beginPath(); ctx.arc(X(s.points[0][0]), Y(s.points[0][1]), 2.5, 0, Math.PI * 2);
        ctx.fill();
      }
    }
  }
}
