// 2D laser scan panel: sensor_msgs/msg/LaserScan drawn around the robot (x forward = up).
//
// The view is scaled to the scan's farthest valid return (rounded up to a round number of
// metres), not to range_max: a 30 m lidar in a 10 x 8 m room filled a fifth of the panel
// with unlabeled rings at 1, 7, 13 m. Each ring says its distance. The scale grows at once
// and shrinks only after SHRINK_AFTER scans that all fit in half of it, so it does not
// jump from scan to scan.

const EXTENTS_M = [0.5, 1, 2, 3, 5, 10, 15, 20, 30, 50, 100, 200];
const RING_STEPS_M = [0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50];
const SHRINK_AFTER = 20;

/** The smallest round extent (m) that holds *r* metres with a 10 % margin. */
export function extentFor(r) {
  return EXTENTS_M.find((e) => e >= r * 1.1) ?? EXTENTS_M[EXTENTS_M.length - 1];
}

/** Ring spacing (m) for an extent: 2 to 5 rings. */
export function ringStep(extent) {
  return RING_STEPS_M.find((s) => extent / s <= 5) ?? RING_STEPS_M[RING_STEPS_M.length - 1];
}

export class ScanView {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.latest = null;
    this.extent = null; // metres from the centre to the panel's edge
    this.small = 0; // consecutive scans that fit in half of the extent
  }

  update(msg) {
    this.latest = msg;
  }

  /** Another robot's page: forget its scale and blank what the last one showed. */
  reset() {
    this.latest = null;
    this.extent = null;
    this.small = 0;
    this.ctx.fillStyle = "#101418";
    this.ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    delete this.canvas.dataset.beams;
  }

  /** Farthest valid return of *msg* (m), or 0. */
  farthest(msg) {
    let far = 0;
    const ranges = msg.ranges;
    for (let i = 0; i < ranges.length; i++) {
      const r = ranges[i];
      if (r >= msg.range_min && r <= msg.range_max && r > far) far = r;
    }
    return far;
  }

  /** The extent to draw *msg* at: grows at once, shrinks after a run of small scans. */
  scaleFor(msg) {
    const want = extentFor(Math.max(this.farthest(msg), 0.1));
    if (this.extent === null || want > this.extent) {
      this.extent = want;
      this.small = 0;
    } else if (want * 2 <= this.extent) {
      if (++this.small >= SHRINK_AFTER) {
        this.extent = want;
        this.small = 0;
      }
    } else {
      this.small = 0;
    }
    return this.extent;
  }

  render() {
    const msg = this.latest;
    if (!msg) return;
    this.latest = null;
    const { ctx, canvas } = this;
    const w = canvas.width, h = canvas.height;
    ctx.fillStyle = "#101418";
    ctx.fillRect(0, 0, w, h);
    const extent = this.scaleFor(msg);
    const scale = (Math.min(w, h) / 2 - 4) / extent; // px per m
    const step = ringStep(extent);
    ctx.strokeStyle = "#2a3540";
    ctx.fillStyle = "#8b949e";
    ctx.font = "12px system-ui, sans-serif";
    ctx.textBaseline = "bottom";
    for (let i = 1; i * step <= extent + 1e-9; i++) {
      const r = i * step;
      ctx.beginPath();
      ctx.arc(w / 2, h / 2, r * scale, 0, 2 * Math.PI);
      ctx.stroke();
      // The label sits on the ring, up and to the right of the robot (45°).
      const d = (r * scale) / Math.SQRT2;
      ctx.fillText(`${+r.toFixed(1)} m`, w / 2 + d + 2, h / 2 - d - 2);
    }
    ctx.fillStyle = "#ff9d2e";
    const ranges = msg.ranges;
    for (let i = 0; i < ranges.length; i++) {
      const r = ranges[i];
      if (!(r >= msg.range_min && r <= msg.range_max)) continue;
      const a = msg.angle_min + i * msg.angle_increment;
      ctx.fillRect(w / 2 - Math.sin(a) * r * scale - 1, h / 2 - Math.cos(a) * r * scale - 1, 3, 3);
    }
    ctx.fillStyle = "#4fc3f7";
    ctx.beginPath();
    ctx.moveTo(w / 2, h / 2 - 8);
    ctx.lineTo(w / 2 - 5, h / 2 + 5);
    ctx.lineTo(w / 2 + 5, h / 2 + 5);
    ctx.fill();
    canvas.dataset.beams = String(ranges.length);
    canvas.dataset.extentM = String(extent);
    canvas.dataset.ringStepM = String(step);
  }
}
