// 2D laser scan panel: sensor_msgs/msg/LaserScan drawn around the robot (x forward = up).

export class ScanView {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.latest = null;
  }

  update(msg) {
    this.latest = msg;
  }

  render() {
    const msg = this.latest;
    if (!msg) return;
    this.latest = null;
    const { ctx, canvas } = this;
    const w = canvas.width, h = canvas.height;
    ctx.fillStyle = "#101418";
    ctx.fillRect(0, 0, w, h);
    const maxR = msg.range_max > 0 && Number.isFinite(msg.range_max) ? Math.min(msg.range_max, 30) : 10;
    const scale = (Math.min(w, h) / 2 - 4) / maxR; // px per m
    ctx.strokeStyle = "#2a3540";
    for (let r = 1; r <= maxR; r += Math.max(1, Math.round(maxR / 5))) {
      ctx.beginPath();
      ctx.arc(w / 2, h / 2, r * scale, 0, 2 * Math.PI);
      ctx.stroke();
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
  }
}
