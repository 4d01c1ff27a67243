// visualization_msgs Marker / MarkerArray kept by (ns, id) and drawn top-down on a 2D
// map context. Bounded: at most MAX_MARKERS; the oldest is evicted (and counted).

import { yawOf } from "./odom.js";

const MAX_MARKERS = 2000;
const T = { ARROW: 0, CUBE: 1, SPHERE: 2, CYLINDER: 3, LINE_STRIP: 4, LINE_LIST: 5, CUBE_LIST: 6, SPHERE_LIST: 7, POINTS: 8, TEXT: 9 };
const DELETE = 2;
const DELETEALL = 3;

export class MarkerStore {
  constructor() {
    this.markers = new Map();
    this.evicted = 0;
  }

  /** Apply a Marker or MarkerArray message. */
  apply(msg) {
    for (const m of msg.markers ?? [msg]) this.one(m);
  }

  one(m) {
    const key = `${m.ns}/${m.id}`;
    if (m.action === DELETEALL) return this.markers.clear();
    if (m.action === DELETE) return void this.markers.delete(key);
    this.markers.delete(key); // re-insert: Map order is then least recently updated first
    this.markers.set(key, m);
    if (this.markers.size > MAX_MARKERS) {
      this.markers.delete(this.markers.keys().next().value);
      this.evicted++;
    }
  }

  /**
   * Draw every marker.
   * @param {CanvasRenderingContext2D} ctx
   * @param {(x: number, y: number) => [number, number]} toPx world (m) -> canvas pixels
   * @param {number} scale pixels per metre
   */
  draw(ctx, toPx, scale) {
    for (const m of this.markers.values()) drawMarker(ctx, m, toPx, scale);
  }
}

function rgba(c) {
  const a = c.a > 0 ? c.a : 1;
  return `rgba(${Math.round(c.r * 255)},${Math.round(c.g * 255)},${Math.round(c.b * 255)},${a})`;
}

function drawMarker(ctx, m, toPx, scale) {
  const p = m.pose.position;
  const yaw = yawOf(m.pose.orientation);
  // Points of list markers are in the marker's own frame: rotate and offset by its pose.
  const local = (q) => toPx(p.x + q.x * Math.cos(yaw) - q.y * Math.sin(yaw), p.y + q.x * Math.sin(yaw) + q.y * Math.cos(yaw));
  ctx.fillStyle = ctx.strokeStyle = rgba(m.color);
  ctx.lineWidth = Math.max(1, m.scale.x * scale);
  const [cx, cy] = toPx(p.x, p.y);
  switch (m.type) {
    case T.ARROW: {
      const len = Math.max(m.scale.x, 0.1) * scale;
      arrow(ctx, cx, cy, cx + len * Math.cos(yaw), cy - len * Math.sin(yaw), Math.max(2, m.scale.y * scale));
      break;
    }
    case T.CUBE:
    case T.CYLINDER:
      ctx.save();
      ctx.translate(cx, cy);
      ctx.rotate(-yaw);
      ctx.fillRect((-m.scale.x * scale) / 2, (-m.scale.y * scale) / 2, m.scale.x * scale, m.scale.y * scale);
      ctx.restore();
      break;
    case T.SPHERE:
      ctx.beginPath();
      ctx.arc(cx, cy, Math.max(1, (m.scale.x * scale) / 2), 0, 2 * Math.PI);
      ctx.fill();
      break;
    case T.LINE_STRIP:
    case T.LINE_LIST: {
      ctx.beginPath();
      m.points.forEach((q, i) => {
        const [x, y] = local(q);
        const move = m.type === T.LINE_STRIP ? i === 0 : i % 2 === 0;
        if (move) ctx.moveTo(x, y);
        else ctx.lineTo(x, y);
      });
      ctx.stroke();
      break;
    }
    case T.CUBE_LIST:
    case T.SPHERE_LIST:
    case T.POINTS: {
      const s = Math.max(2, m.scale.x * scale);
      m.points.forEach((q, i) => {
        if (m.colors?.[i]) ctx.fillStyle = rgba(m.colors[i]);
        const [x, y] = local(q);
        ctx.fillRect(x - s / 2, y - s / 2, s, s);
      });
      break;
    }
    case T.TEXT:
      ctx.font = `${Math.max(10, m.scale.z * scale)}px sans-serif`;
      ctx.textAlign = "center";
      ctx.fillText(m.text, cx, cy);
      break;
    default:
      break; // MESH_RESOURCE and TRIANGLE_LIST have no top-down 2D form here
  }
}

export function arrow(ctx, x0, y0, x1, y1, head = 8) {
  const a = Math.atan2(y1 - y0, x1 - x0);
  ctx.beginPath();
  ctx.moveTo(x0, y0);
  ctx.lineTo(x1, y1);
  ctx.stroke();
  ctx.beginPath();
  ctx.moveTo(x1, y1);
  ctx.lineTo(x1 - head * Math.cos(a - 0.45), y1 - head * Math.sin(a - 0.45));
  ctx.lineTo(x1 - head * Math.cos(a + 0.45), y1 - head * Math.sin(a + 0.45));
  ctx.fill();
}
