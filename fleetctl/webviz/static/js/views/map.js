// Map panel: OccupancyGrid (or an empty 1 m grid), the robot's pose and path, markers, and
// click-and-drag tools for a navigation goal and an initial pose (press = position, drag =
// heading; or typed, poseentry.js, or keyed on the focused map, drawn as a preview).
// Coordinates are drawn in the frame the messages use; there is no TF here.

import { MarkerStore, arrow } from "./markers.js";
import { yawOf } from "./odom.js";

const MAX_PATH = 2000; // pose history points kept (oldest dropped)
const JUMP_M = 1.0; // a pose this far from the last one is a jump, not driving
const SCALE_BAR_MAX_PX = 120; // canvas px the scale bar may take

/**
 * The scale bar at *pxPerM* canvas px per metre: the longest round length (1, 2 or 5 x 10^k
 * m) that fits in *maxPx*, its length in canvas px and its label ("2 m", "50 cm").
 * @returns {{m: number, px: number, label: string}}
 */
export function scaleBar(pxPerM, maxPx = SCALE_BAR_MAX_PX) {
  const fits = maxPx / pxPerM;
  const decade = 10 ** Math.floor(Math.log10(fits));
  const m = [5, 2, 1].map((k) => k * decade).find((v) => v <= fits * (1 + 1e-9));
  const label = m >= 1 ? `${Math.round(m)} m` : `${Math.round(m * 100)} cm`;
  return { m, px: m * pxPerM, label };
}

export class MapView {
  /**
   * @param {HTMLCanvasElement} canvas
   * @param {(kind: "goal"|"initialpose", x: number, y: number, yaw: number) => void} onPose
   * @param {{scale?: HTMLElement, onAim?: (kind: string, x: number, y: number, yaw: number|null) => void,
   *          onKey?: (e: KeyboardEvent) => boolean}} [opts]
   *   scale: the scale bar over the canvas (a child `.bar` and `.label`); onAim: where a
   *   armed tool points (yaw null until the press), as the pointer moves; onKey: a key on
   *   the focused canvas while a tool is armed, true when it was used
   */
  constructor(canvas, onPose, { scale = null, onAim = () => {}, onKey = () => false } = {}) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.onPose = onPose;
    this.scaleEl = scale;
    this.onAim = onAim;
    this.scale = 40; // px per m
    this.center = { x: 0, y: 0 }; // world point at the canvas centre (m)
    this.pose = null;
    this.path = [];
    this.plan = null;
    this.grid = null;
    this.markers = new MarkerStore();
    this.tool = null;
    this.drag = null;
    this.preview = null; // the pose typed or keyed for the armed tool, {x, y, yaw}, or null
    this.pan = null; // a drag without a tool moves the view
    this.sent = []; // the last goal and initial pose sent from this page, drawn until reset
    this.dirty = true;
    canvas.addEventListener("pointerdown", (e) => this.down(e));
    canvas.addEventListener("pointermove", (e) => this.move(e));
    canvas.addEventListener("pointerup", (e) => this.up(e));
    canvas.addEventListener("pointercancel", () => this.cancelDrag());
    canvas.addEventListener("keydown", (e) => {
      if (this.tool && !this.drag && onKey(e)) e.preventDefault(); // an arrow must not scroll the page
    });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.scale = Math.min(400, Math.max(2, this.scale * (e.deltaY < 0 ? 1.2 : 1 / 1.2)));
      this.dirty = true;
    });
  }

  /** Forget the previous robot's pose, path, plan, grid and markers. */
  reset() {
    this.pose = null;
    this.path = [];
    this.plan = null;
    this.grid = null;
    this.markers = new MarkerStore();
    this.sent = [];
    this.dirty = true;
  }

  toPx = (x, y) => [this.canvas.width / 2 + (x - this.center.x) * this.scale, this.canvas.height / 2 - (y - this.center.y) * this.scale];

  toWorld(px, py) {
    return { x: this.center.x + (px - this.canvas.width / 2) / this.scale, y: this.center.y - (py - this.canvas.height / 2) / this.scale };
  }

  eventWorld(e) {
    const r = this.canvas.getBoundingClientRect();
    return this.toWorld(((e.clientX - r.left) * this.canvas.width) / r.width, ((e.clientY - r.top) * this.canvas.height) / r.height);
  }

  setTool(tool) {
    this.tool = tool;
    if (!tool) this.setPreview(null);
    this.canvas.style.cursor = tool ? "crosshair" : "grab";
    this.canvas.dataset.tool = tool ?? "";
  }

  /** Drop a press in progress (pan or tool drag); the tool stays armed. */
  cancelDrag() {
    this.drag = null;
    this.pan = null;
    this.dirty = true;
  }

  /**
   * Draw where a typed or keyed pose is, for the armed tool (null: nothing). *reveal*: a
   * pose off the map shown brings the view to it (a dock typed 12 m away was drawn off
   * the canvas); never during a press, whose points are read in the view's coordinates.
   */
  setPreview(pose, reveal = false) {
    this.preview = pose;
    this.dirty = true;
    if (!pose || !reveal || this.drag || this.pan) return;
    const [px, py] = this.toPx(pose.x, pose.y);
    const margin = 0.1 * this.canvas.width;
    if (px < margin || py < margin || px > this.canvas.width - margin || py > this.canvas.height - margin) {
      this.center = { x: pose.x, y: pose.y };
    }
  }

  /** Remember a pose sent from this page, drawn as an arrow where it was aimed. */
  markSent(kind, x, y, yaw) {
    this.sent = [...this.sent.filter((p) => p.kind !== kind), { kind, x, y, yaw }];
    this.dirty = true;
  }

  down(e) {
    if (!this.tool) {
      // No tool: drag to pan (a map whose origin is far from 0, 0 was out of reach).
      this.canvas.setPointerCapture?.(e.pointerId);
      this.pan = { x: e.clientX, y: e.clientY };
      return;
    }
    this.canvas.setPointerCapture?.(e.pointerId);
    const w = this.eventWorld(e);
    this.drag = { start: w, end: w };
    this.dirty = true;
  }

  move(e) {
    if (this.pan) {
      const r = this.canvas.getBoundingClientRect();
      const k = this.canvas.width / r.width / this.scale; // m per CSS px
      this.center = { x: this.center.x - (e.clientX - this.pan.x) * k, y: this.center.y + (e.clientY - this.pan.y) * k };
      this.pan = { x: e.clientX, y: e.clientY };
      this.dirty = true;
      return;
    }
    if (!this.tool) return;
    if (!this.drag) {
      const w = this.eventWorld(e);
      return this.onAim(this.tool, w.x, w.y, null);
    }
    this.drag.end = this.eventWorld(e);
    this.dirty = true;
    const { start, end } = this.drag;
    this.onAim(this.tool, start.x, start.y, yawBetween(start, end));
  }

  up(e) {
    this.pan = null;
    if (!this.drag) return;
    const { start } = this.drag;
    const yaw = yawBetween(start, this.eventWorld(e));
    const tool = this.tool;
    this.drag = null;
    this.setTool(null);
    this.dirty = true;
    this.onPose(tool, start.x, start.y, yaw);
  }

  /** A pose from Odometry / PoseWithCovarianceStamped / PoseStamped (the inner Pose). */
  updatePose(pose) {
    this.pose = { x: pose.position.x, y: pose.position.y, yaw: yawOf(pose.orientation) };
    const last = this.path[this.path.length - 1];
    const step = last ? Math.hypot(last.x - this.pose.x, last.y - this.pose.y) : Infinity;
    if (step > 0.05) {
      // A jump (an initial pose, a relocalization) starts a new piece of path: a straight
      // line across the map from the old place was drawn as if the robot had driven it.
      if (last && step > JUMP_M) this.path.push(null);
      this.path.push({ x: this.pose.x, y: this.pose.y });
      if (this.path.length > MAX_PATH) this.path.shift();
    }
    this.dirty = true;
  }

  updatePlan(msg) {
    this.plan = msg.poses.map((p) => p.pose.position);
    this.dirty = true;
  }

  updateMarkers(msg) {
    this.markers.apply(msg);
    this.dirty = true;
  }

  updateGrid(msg) {
    const { width, height, resolution, origin } = msg.info;
    if (width * height > msg.data.length || width <= 0 || height <= 0) return;
    const img = new ImageData(width, height);
    for (let i = 0; i < width * height; i++) {
      const v = msg.data[i];
      const c = v < 0 ? 90 : 235 - Math.round((Math.min(v, 100) / 100) * 220);
      // Grid row 0 is the bottom (min y): flip so the image's row 0 is the top.
      const row = height - 1 - Math.floor(i / width);
      const o = 4 * (row * width + (i % width));
      img.data[o] = img.data[o + 1] = img.data[o + 2] = c;
      img.data[o + 3] = 255;
    }
    const off = new OffscreenCanvas(width, height);
    off.getContext("2d").putImageData(img, 0, 0);
    this.grid = { image: off, resolution, x: origin.position.x, y: origin.position.y, width, height };
    this.dirty = true;
  }

  render() {
    if (!this.dirty) return;
    this.dirty = false;
    const { ctx, canvas } = this;
    // Sizes in CSS px: the canvas is 640 px wide but shown ~300 px wide in its panel, where
    // the robot's 22 px arrow was a 10 px speck at the end of its path.
    const k = canvas.clientWidth ? Math.max(1, canvas.width / canvas.clientWidth) : 1;
    this.lineScale = k;
    ctx.fillStyle = "#1b2127";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    if (this.grid) {
      const g = this.grid;
      const [x0, y1] = this.toPx(g.x, g.y + g.height * g.resolution);
      ctx.imageSmoothingEnabled = false;
      ctx.drawImage(g.image, x0, y1, g.width * g.resolution * this.scale, g.height * g.resolution * this.scale);
    } else {
      this.drawEmptyGrid();
    }
    this.drawLine(this.path, "#66bb6a");
    if (this.plan) this.drawLine(this.plan, "#29b6f6");
    this.markers.draw(ctx, this.toPx, this.scale);
    if (this.pose) {
      const [x, y] = this.toPx(this.pose.x, this.pose.y);
      ctx.fillStyle = ctx.strokeStyle = "#ffca28";
      ctx.lineWidth = 3 * k;
      arrow(ctx, x, y, x + 22 * k * Math.cos(this.pose.yaw), y - 22 * k * Math.sin(this.pose.yaw), 9 * k);
    }
    for (const p of this.sent) {
      const [x, y] = this.toPx(p.x, p.y);
      ctx.fillStyle = ctx.strokeStyle = p.kind === "goal" ? "#ef5350" : "#ab47bc";
      ctx.lineWidth = 2 * k;
      ctx.beginPath();
      ctx.arc(x, y, 5 * k, 0, 2 * Math.PI);
      ctx.stroke();
      arrow(ctx, x, y, x + 26 * k * Math.cos(p.yaw), y - 26 * k * Math.sin(p.yaw), 9 * k);
    }
    if (this.preview && this.tool && !this.drag) {
      // Dashed: not sent yet.
      const p = this.preview;
      const [x, y] = this.toPx(p.x, p.y);
      ctx.fillStyle = ctx.strokeStyle = this.tool === "goal" ? "#ef5350" : "#ab47bc";
      ctx.lineWidth = 3 * k;
      ctx.setLineDash([6 * k, 4 * k]);
      ctx.beginPath();
      ctx.arc(x, y, 7 * k, 0, 2 * Math.PI);
      ctx.stroke();
      ctx.setLineDash([]);
      arrow(ctx, x, y, x + 30 * k * Math.cos(p.yaw), y - 30 * k * Math.sin(p.yaw), 10 * k);
    }
    if (this.drag) {
      const [x0, y0] = this.toPx(this.drag.start.x, this.drag.start.y);
      const [x1, y1] = this.toPx(this.drag.end.x, this.drag.end.y);
      ctx.fillStyle = ctx.strokeStyle = this.tool === "goal" ? "#ef5350" : "#ab47bc";
      ctx.lineWidth = 3 * k;
      arrow(ctx, x0, y0, x1, y1, 10 * k);
    }
    this.renderScale();
  }

  /** The scale bar over the canvas (HTML, as wide as its length is on the canvas). */
  renderScale() {
    if (!this.scaleEl) return;
    const bar = scaleBar(this.scale);
    this.scaleEl.querySelector(".bar").style.width = `${(100 * bar.px) / this.canvas.width}%`;
    this.scaleEl.querySelector(".label").textContent = bar.label;
    this.scaleEl.dataset.m = String(bar.m);
  }

  drawEmptyGrid() {
    const { ctx, canvas } = this;
    ctx.strokeStyle = "#2a3540";
    ctx.lineWidth = 1;
    const tl = this.toWorld(0, 0), br = this.toWorld(canvas.width, canvas.height);
    const step = this.scale < 8 ? 10 : 1; // m between lines
    ctx.beginPath();
    for (let x = Math.ceil(tl.x / step) * step; x <= br.x; x += step) {
      const [px] = this.toPx(x, 0);
      ctx.moveTo(px, 0);
      ctx.lineTo(px, canvas.height);
    }
    for (let y = Math.ceil(br.y / step) * step; y <= tl.y; y += step) {
      const [, py] = this.toPx(0, y);
      ctx.moveTo(0, py);
      ctx.lineTo(canvas.width, py);
    }
    ctx.stroke();
  }

  drawLine(points, color) {
    if (points.length < 2) return;
    const { ctx } = this;
    ctx.strokeStyle = color;
    ctx.lineWidth = 2 * (this.lineScale ?? 1);
    ctx.beginPath();
    let pen = false; // null in a path: a jump, lift the pen
    for (const p of points) {
      if (!p) {
        pen = false;
        continue;
      }
      const [x, y] = this.toPx(p.x, p.y);
      if (pen) ctx.lineTo(x, y);
      else ctx.moveTo(x, y);
      pen = true;
    }
    ctx.stroke();
  }
}

/** Heading (rad) from a press to a release; 0 for a press without a drag. */
function yawBetween(start, end) {
  return Math.hypot(end.x - start.x, end.y - start.y) > 1e-3 ? Math.atan2(end.y - start.y, end.x - start.x) : 0;
}
