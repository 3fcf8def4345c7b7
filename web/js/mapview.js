// The map: a canvas that draws landmarks with their 2-sigma ellipses, robots with their
// trajectories and particle clouds, and ground truth, in metres, with pan and zoom (mouse,
// wheel, touch pinch), fit-to-map, axes, a grid and a scale bar.
//
// World frame: x to the right, y up (the filter's frame). Screen: x right, y down.

import { h } from "./util.js";

const TWO_PI = Math.PI * 2;
/** Radius [px] of a landmark's dot. */
const DOT_RADIUS = 3.5;
/** Landmark ids are written only while at most this many landmarks are on screen. */
const MAX_LABELS = 400;
/** Frames whose draw times are kept for `frameStats`. */
const FRAME_WINDOW = 120;

/** A "nice" step (1, 2 or 5 times a power of ten) of at least `raw`. */
function niceStep(raw) {
  const p = Math.pow(10, Math.floor(Math.log10(raw)));
  for (const m of [1, 2, 5, 10]) if (m * p >= raw) return m * p;
  return 10 * p;
}

function fmtMetres(v, step) {
  const digits = step >= 1 ? 0 : Math.min(3, Math.ceil(-Math.log10(step)));
  return v.toFixed(digits);
}

/** Axes of the 2-sigma ellipse of the 2x2 covariance [[a, b], [b, c]]: [r1, r2, angle]. */
export function ellipse2Sigma(a, b, c) {
  if (![a, b, c].every(Number.isFinite)) return null;
  const mid = (a + c) / 2;
  const d = Math.sqrt(((a - c) / 2) ** 2 + b * b);
  const l1 = Math.max(mid + d, 0);
  const l2 = Math.max(mid - d, 0);
  const angle = 0.5 * Math.atan2(2 * b, a - c);
  return [2 * Math.sqrt(l1), 2 * Math.sqrt(l2), angle];
}

/** What drawing a landmark needs, computed once per state: position, ellipse, label. */
function landmarkGeometry(landmarks) {
  return landmarks.map((l) => ({
    x: l.mean[0],
    y: l.mean[1],
    e: l.cov ? ellipse2Sigma(l.cov[0], l.cov[1], l.cov[3]) : null,
    label: l.id === null || l.id === undefined ? null : String(l.id),
  }));
}

export class MapView {
  /**
   * @param {HTMLElement} host element the map fills
   * @param {object} opts `{title, compact}`
   */
  constructor(host, opts = {}) {
    this.opts = opts;
    this.show = { particles: true, ellipses: true, trajectories: true, truth: true, ids: true };
    this.poseMode = "best";
    this.data = { landmarks: [], robots: [], trajectories: {}, particles: {}, truth: null };
    this.colors = {};
    // View: world point at the canvas centre and pixels per metre.
    this.cx = 0;
    this.cy = 0;
    this.scale = 40;
    this.follow = true; // refit as the map grows until the user pans or zooms
    this.pointers = new Map();
    this.dirty = true;

    this.canvas = h("canvas.map-canvas", { "data-testid": "map-canvas", "aria-label": "map" });
    this.legend = h("div.map-legend", { "data-testid": "map-legend" });
    this.title = h("div.map-title", {}, opts.title || "");
    if (!opts.title) this.title.hidden = true;
    const btn = (label, title, fn, testid) =>
      h("button.map-btn", { type: "button", title, "aria-label": title, onclick: fn,
        "data-testid": testid }, label);
    this.controls = h("div.map-controls", {},
      btn("+", "Zoom in", () => this.zoomBy(1.5), "zoom-in"),
      btn("−", "Zoom out", () => this.zoomBy(1 / 1.5), "zoom-out"),
      btn("Fit", "Fit the map to the view", () => this.fit(true), "fit"));
    this.empty = h("div.map-empty", {}, "Waiting for data…");
    this.root = h("div.map", {}, this.canvas, this.title, this.legend, this.controls, this.empty);
    host.append(this.root);
    this.ctx = this.canvas.getContext("2d");
    this.bindInput();
    this.resizeObserver = new ResizeObserver(() => { this.dirty = true; this.schedule(); });
    this.resizeObserver.observe(this.root);
    this.schedule();
  }

  destroy() {
    this.resizeObserver.disconnect();
    if (this.raf) cancelAnimationFrame(this.raf);
    this.destroyed = true;
    this.root.remove();
  }

  /**
   * @param {object} d `{landmarks, robots: [{id, pose, mode}], trajectories: {id: [[t,x,y,th]]},
   *   particles: {id: [[x,y,th,w]]}, truth: {robots, landmarks} | null, colors: {id: css}}`
   */
  setData(d) {
    if (d.landmarks && d.landmarks !== this.data.landmarks) this.geom = landmarkGeometry(d.landmarks);
    this.data = { ...this.data, ...d };
    if (d.colors) this.colors = d.colors;
    this.empty.hidden = this.hasContent();
    if (this.follow) this.fit(false);
    this.renderLegend();
    this.dirty = true;
    this.schedule();
  }

  setShow(key, on) {
    this.show[key] = on;
    this.renderLegend();
    this.dirty = true;
    this.schedule();
  }

  hasContent() {
    const d = this.data;
    return d.landmarks.length > 0 || d.robots.some((r) => r.pose) ||
      Object.values(d.trajectories || {}).some((t) => t.length > 0);
  }

  /** World extent of what is drawn: [xmin, ymin, xmax, ymax] or null. */
  extent() {
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    const add = (x, y) => {
      if (!Number.isFinite(x) || !Number.isFinite(y)) return;
      x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y);
    };
    const d = this.data;
    for (const l of d.landmarks) add(l.mean[0], l.mean[1]);
    for (const r of d.robots) if (r.pose) add(r.pose.x, r.pose.y);
    for (const tr of Object.values(d.trajectories || {})) for (const p of tr) add(p[1], p[2]);
    if (d.truth && this.show.truth) {
      for (const l of d.truth.landmarks || []) add(l.x, l.y);
      for (const tr of Object.values(d.truth.robots || {})) for (const p of tr) add(p[1], p[2]);
    }
    if (x0 > x1) return null;
    return [x0, y0, x1, y1];
  }

  size() {
    const r = this.canvas.getBoundingClientRect();
    return [Math.max(r.width, 1), Math.max(r.height, 1)];
  }

  /** Fits the view to the map; `user` re-enables following the map as it grows. */
  fit(user) {
    if (user) this.follow = true;
    const e = this.extent();
    if (!e) return;
    const [w, h] = this.size();
    const pad = 1.0; // metres around the content
    const ew = Math.max(e[2] - e[0] + 2 * pad, 2);
    const eh = Math.max(e[3] - e[1] + 2 * pad, 2);
    // Leave room for the legend on the left and the axis labels.
    const usableW = Math.max(w - 60, 50);
    const usableH = Math.max(h - 50, 50);
    this.scale = Math.min(usableW / ew, usableH / eh);
    this.cx = (e[0] + e[2]) / 2 - 10 / this.scale;
    this.cy = (e[1] + e[3]) / 2 - 8 / this.scale;
    this.dirty = true;
    this.schedule();
  }

  zoomBy(f, sx, sy) {
    const [w, h] = this.size();
    if (sx === undefined) { sx = w / 2; sy = h / 2; }
    const [wx, wy] = this.toWorld(sx, sy);
    this.scale = Math.min(Math.max(this.scale * f, 0.5), 5000);
    // Keep the world point under the cursor in place.
    this.cx = wx - (sx - w / 2) / this.scale;
    this.cy = wy + (sy - h / 2) / this.scale;
    this.follow = false;
    this.dirty = true;
    this.schedule();
  }

  toScreen(x, y) {
    // Within a frame the canvas's size is read once (reading it costs a layout query).
    const [w, h] = this.frameSize || this.size();
    return [(x - this.cx) * this.scale + w / 2, h / 2 - (y - this.cy) * this.scale];
  }

  /** Draw times of the last frames [ms]: `{frames, mean, max}`. */
  frameStats() {
    const t = this.frameMs || [];
    return {
      frames: this.frames || 0,
      mean: t.length ? t.reduce((a, b) => a + b, 0) / t.length : 0,
      max: t.length ? Math.max(...t) : 0,
    };
  }

  toWorld(sx, sy) {
    const [w, h] = this.size();
    return [this.cx + (sx - w / 2) / this.scale, this.cy - (sy - h / 2) / this.scale];
  }

  bindInput() {
    const c = this.canvas;
    c.addEventListener("wheel", (e) => {
      e.preventDefault();
      const r = c.getBoundingClientRect();
      this.zoomBy(Math.exp(-e.deltaY * 0.0015), e.clientX - r.left, e.clientY - r.top);
    }, { passive: false });
    c.addEventListener("dblclick", (e) => {
      const r = c.getBoundingClientRect();
      this.zoomBy(2, e.clientX - r.left, e.clientY - r.top);
    });
    c.addEventListener("pointerdown", (e) => {
      c.setPointerCapture(e.pointerId);
      this.pointers.set(e.pointerId, { x: e.clientX, y: e.clientY });
    });
    const up = (e) => {
      this.pointers.delete(e.pointerId);
      this.pinch = null;
    };
    c.addEventListener("pointerup", up);
    c.addEventListener("pointercancel", up);
    c.addEventListener("pointermove", (e) => {
      const prev = this.pointers.get(e.pointerId);
      if (!prev) return;
      const cur = { x: e.clientX, y: e.clientY };
      if (this.pointers.size === 1) {
        this.cx -= (cur.x - prev.x) / this.scale;
        this.cy += (cur.y - prev.y) / this.scale;
        this.follow = false;
        this.dirty = true;
        this.schedule();
      } else if (this.pointers.size === 2) {
        const [a, b] = [...this.pointers.entries()].map(([id, p]) =>
          (id === e.pointerId ? cur : p));
        const dist = Math.hypot(a.x - b.x, a.y - b.y);
        if (this.pinch) {
          const r = c.getBoundingClientRect();
          this.zoomBy(dist / this.pinch, (a.x + b.x) / 2 - r.left, (a.y + b.y) / 2 - r.top);
        }
        this.pinch = dist;
      }
      this.pointers.set(e.pointerId, cur);
    });
  }

  schedule() {
    if (this.raf || this.destroyed) return;
    this.raf = requestAnimationFrame(() => {
      this.raf = null;
      if (this.dirty) this.draw();
    });
  }

  robotPose(r) {
    return r.pose || null;
  }

  renderLegend() {
    const d = this.data;
    const items = [];
    for (const r of d.robots) {
      const col = this.colors[r.id] || "#333";
      const mode = r.mode && r.mode !== "mapping" ? ` · ${r.mode.replace("_", " ")}` : "";
      items.push(h("div.lg-item", { "data-robot": r.id },
        h("span.lg-robot", { style: { background: col } }),
        `robot ${r.id}${mode}`));
    }
    items.push(h("div.lg-item", {}, h("span.lg-landmark"),
      this.show.ellipses ? "landmark, 2σ ellipse" : "landmark"));
    if (this.show.particles && Object.keys(d.particles || {}).length) {
      items.push(h("div.lg-item", {}, h("span.lg-particles"), "particles (sample)"));
    }
    if (d.truth && this.show.truth) {
      items.push(h("div.lg-item", {}, h("span.lg-truth"), "ground truth"));
    }
    items.push(h("div.lg-item.lg-mode", {},
      `pose: ${this.poseMode === "best" ? "best particle" : "weighted mean"}`));
    this.legend.replaceChildren(...items);
  }

  draw() {
    const started = performance.now();
    this.frameSize = null;
    this.drawFrame();
    this.frameSize = null;
    this.frameMs = this.frameMs || [];
    this.frameMs.push(performance.now() - started);
    if (this.frameMs.length > FRAME_WINDOW) this.frameMs.shift();
    this.frames = (this.frames || 0) + 1;
  }

  drawFrame() {
    this.dirty = false;
    const dpr = window.devicePixelRatio || 1;
    const [w, hgt] = this.size();
    this.frameSize = [w, hgt];
    const pw = Math.round(w * dpr), ph = Math.round(hgt * dpr);
    if (this.canvas.width !== pw || this.canvas.height !== ph) {
      this.canvas.width = pw;
      this.canvas.height = ph;
      if (this.follow) this.fit(false);
    }
    const ctx = this.ctx;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, hgt);
    ctx.fillStyle = "#fbfcfe";
    ctx.fillRect(0, 0, w, hgt);
    this.drawGrid(ctx, w, hgt);
    const d = this.data;
    if (d.truth && this.show.truth) this.drawTruth(ctx, d.truth);
    this.drawLandmarks(ctx, w, hgt);
    if (this.show.trajectories) {
      for (const [id, tr] of Object.entries(d.trajectories || {})) {
        this.drawPath(ctx, tr, this.colors[id] || "#333", 2, []);
      }
    }
    if (this.show.particles) {
      for (const [id, ps] of Object.entries(d.particles || {})) {
        this.drawParticles(ctx, ps, this.colors[id] || "#333");
      }
    }
    for (const r of d.robots) this.drawRobot(ctx, r);
    this.drawScaleBar(ctx, w, hgt);
  }

  drawGrid(ctx, w, hgt) {
    const step = niceStep(70 / this.scale);
    const [x0, y1] = this.toWorld(0, 0);
    const [x1, y0] = this.toWorld(w, hgt);
    ctx.lineWidth = 1;
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillStyle = "#6b7280";
    const major = step * 5;
    for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
      const [sx] = this.toScreen(x, 0);
      const isAxis = Math.abs(x) < step / 2;
      const isMajor = Math.abs(x / major - Math.round(x / major)) < 1e-6;
      ctx.strokeStyle = isAxis ? "#94a3b8" : isMajor ? "#e2e8f0" : "#eef2f7";
      ctx.beginPath(); ctx.moveTo(Math.round(sx) + 0.5, 0);
      ctx.lineTo(Math.round(sx) + 0.5, hgt); ctx.stroke();
      // Labels along the bottom, clear of the y labels at the right edge.
      if (sx < w - 40) {
        ctx.textAlign = "center"; ctx.textBaseline = "bottom";
        ctx.fillText(fmtMetres(x, step), sx, hgt - 4);
      }
    }
    for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
      const [, sy] = this.toScreen(0, y);
      const isAxis = Math.abs(y) < step / 2;
      const isMajor = Math.abs(y / major - Math.round(y / major)) < 1e-6;
      ctx.strokeStyle = isAxis ? "#94a3b8" : isMajor ? "#e2e8f0" : "#eef2f7";
      ctx.beginPath(); ctx.moveTo(0, Math.round(sy) + 0.5);
      ctx.lineTo(w, Math.round(sy) + 0.5); ctx.stroke();
      if (sy < hgt - 22 && sy > 10) {
        ctx.textAlign = "right"; ctx.textBaseline = "middle";
        ctx.fillText(fmtMetres(y, step), w - 4, sy);
      }
    }
    ctx.fillStyle = "#475569";
    ctx.font = "600 11px system-ui, sans-serif";
    ctx.textAlign = "right"; ctx.textBaseline = "bottom";
    ctx.fillText("x [m] →", w - 30, hgt - 18);
    ctx.textAlign = "right"; ctx.textBaseline = "top";
    ctx.fillText("↑ y [m]", w - 30, 50);
  }

  drawScaleBar(ctx, w, hgt) {
    const metres = niceStep(110 / this.scale);
    const px = metres * this.scale;
    const x = 14, y = hgt - 26;
    ctx.fillStyle = "rgba(255,255,255,0.85)";
    ctx.fillRect(x - 6, y - 18, px + 12, 30);
    ctx.strokeStyle = "#111827";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(x, y - 5); ctx.lineTo(x, y); ctx.lineTo(x + px, y); ctx.lineTo(x + px, y - 5);
    ctx.stroke();
    ctx.fillStyle = "#111827";
    ctx.font = "600 12px system-ui, sans-serif";
    ctx.textAlign = "center"; ctx.textBaseline = "bottom";
    ctx.fillText(`${metres >= 1 ? metres : metres.toPrecision(1)} m`, x + px / 2, y - 4);
  }

  /**
   * The landmarks on screen (with their ellipses' margin), each as one subpath of a few
   * shared paths: one fill and one stroke for every ellipse, one fill for every dot.
   */
  drawLandmarks(ctx, w, hgt) {
    const s = this.scale;
    const shown = [];
    for (const g of this.geom || []) {
      const [sx, sy] = this.toScreen(g.x, g.y);
      const r = g.e ? Math.max(g.e[0] * s, 4) : 4;
      if (sx < -r || sy < -r || sx > w + r || sy > hgt + r) continue;
      shown.push([g, sx, sy]);
    }
    if (this.show.ellipses) {
      ctx.beginPath();
      for (const [g, sx, sy] of shown) {
        if (!g.e) continue;
        const rx = Math.max(g.e[0] * s, 0.5), ry = Math.max(g.e[1] * s, 0.5);
        // An ellipse inside its landmark's dot cannot be seen: not drawn.
        if (rx <= DOT_RADIUS && ry <= DOT_RADIUS) continue;
        const rot = -g.e[2];
        ctx.moveTo(sx + rx * Math.cos(rot), sy + rx * Math.sin(rot));
        ctx.ellipse(sx, sy, rx, ry, rot, 0, TWO_PI);
      }
      ctx.fillStyle = "rgba(20, 33, 61, 0.08)";
      ctx.fill();
      ctx.strokeStyle = "rgba(20, 33, 61, 0.55)";
      ctx.lineWidth = 1.2;
      ctx.stroke();
    }
    ctx.beginPath();
    for (const [, sx, sy] of shown) {
      ctx.moveTo(sx + DOT_RADIUS, sy);
      ctx.arc(sx, sy, DOT_RADIUS, 0, TWO_PI);
    }
    ctx.fillStyle = "#14213d";
    ctx.fill();
    if (this.show.ids && shown.length <= MAX_LABELS) {
      ctx.font = "600 11px system-ui, sans-serif";
      ctx.textAlign = "left"; ctx.textBaseline = "bottom";
      ctx.lineWidth = 3; ctx.strokeStyle = "rgba(255,255,255,0.9)";
      ctx.fillStyle = "#14213d";
      for (const [g, sx, sy] of shown) {
        if (g.label === null) continue;
        ctx.strokeText(g.label, sx + 5, sy - 3);
        ctx.fillText(g.label, sx + 5, sy - 3);
      }
    }
  }

  drawTruth(ctx, truth) {
    for (const [id, tr] of Object.entries(truth.robots || {})) {
      this.drawPath(ctx, tr, this.colors[id] || "#555", 1.5, [5, 4], 0.55);
    }
    // One path of the squares on screen (thousands of separate strokes cost a frame).
    const [w, hgt] = this.frameSize || this.size();
    ctx.beginPath();
    for (const l of truth.landmarks || []) {
      const [sx, sy] = this.toScreen(l.x, l.y);
      if (sx < -5 || sy < -5 || sx > w + 5 || sy > hgt + 5) continue;
      ctx.rect(sx - 5, sy - 5, 10, 10);
    }
    ctx.strokeStyle = "#6b7280";
    ctx.lineWidth = 1.5;
    ctx.stroke();
  }

  drawPath(ctx, tr, color, width, dash, alpha = 0.9) {
    if (!tr || tr.length < 2) return;
    ctx.save();
    ctx.globalAlpha = alpha;
    ctx.strokeStyle = color;
    ctx.lineWidth = width;
    ctx.lineJoin = "round";
    ctx.setLineDash(dash);
    ctx.beginPath();
    // Skip points closer than a pixel: long runs have many thousands.
    let [lx, ly] = this.toScreen(tr[0][1], tr[0][2]);
    ctx.moveTo(lx, ly);
    for (let i = 1; i < tr.length; i++) {
      const [sx, sy] = this.toScreen(tr[i][1], tr[i][2]);
      if (Math.abs(sx - lx) + Math.abs(sy - ly) < 1 && i < tr.length - 1) continue;
      ctx.lineTo(sx, sy);
      lx = sx; ly = sy;
    }
    ctx.stroke();
    ctx.restore();
  }

  drawParticles(ctx, ps, color) {
    ctx.save();
    ctx.fillStyle = color;
    ctx.globalAlpha = 0.45;
    for (const p of ps) {
      const [sx, sy] = this.toScreen(p[0], p[1]);
      ctx.fillRect(sx - 1.5, sy - 1.5, 3, 3);
    }
    ctx.restore();
  }

  drawRobot(ctx, r) {
    const p = this.robotPose(r);
    if (!p) return;
    const color = this.colors[r.id] || "#333";
    const [sx, sy] = this.toScreen(p.x, p.y);
    const a = -p.theta; // screen y is flipped
    const size = 11;
    ctx.save();
    ctx.translate(sx, sy);
    if (r.mode === "localizing") {
      ctx.setLineDash([3, 3]);
      ctx.strokeStyle = color;
      ctx.lineWidth = 1.5;
      ctx.beginPath(); ctx.arc(0, 0, size + 6, 0, TWO_PI); ctx.stroke();
      ctx.setLineDash([]);
    }
    ctx.rotate(a);
    ctx.beginPath();
    ctx.moveTo(size, 0);
    ctx.lineTo(-size * 0.7, size * 0.6);
    ctx.lineTo(-size * 0.4, 0);
    ctx.lineTo(-size * 0.7, -size * 0.6);
    ctx.closePath();
    ctx.fillStyle = color;
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = 2;
    ctx.stroke();
    ctx.fill();
    ctx.restore();
    ctx.font = "700 12px system-ui, sans-serif";
    ctx.textAlign = "left"; ctx.textBaseline = "top";
    ctx.lineWidth = 3; ctx.strokeStyle = "rgba(255,255,255,0.9)";
    ctx.strokeText(r.id, sx + 9, sy + 6);
    ctx.fillStyle = color;
    ctx.fillText(r.id, sx + 9, sy + 6);
  }
}
