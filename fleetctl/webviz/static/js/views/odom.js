// Odometry panel: nav_msgs/msg/Odometry as position, heading and speed text.

export function yawOf(q) {
  return Math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z));
}

export class OdomView {
  constructor(el) {
    this.el = el;
    this.latest = null;
  }

  update(msg) {
    this.latest = msg;
  }

  /** Another robot's page: its odometry is not the last one's. */
  reset() {
    this.latest = null;
    this.el.textContent = "no odometry yet";
  }

  render() {
    const msg = this.latest;
    if (!msg) return;
    this.latest = null;
    const p = msg.pose.pose.position;
    const v = msg.twist.twist.linear;
    const speed = Math.hypot(v.x, v.y, v.z);
    const yawDeg = (yawOf(msg.pose.pose.orientation) * 180) / Math.PI;
    this.el.textContent =
      `x ${p.x.toFixed(2)} m   y ${p.y.toFixed(2)} m   heading ${yawDeg.toFixed(0)}°\n` +
      `speed ${speed.toFixed(2)} m/s   turn ${msg.twist.twist.angular.z.toFixed(2)} rad/s   frame ${msg.header.frame_id}`;
  }
}
