// Extract xyz from sensor_msgs/msg/PointCloud2 into a Float32Array, decimating to at
// most maxPoints (every k-th point) so a phone is not asked to draw a million points.

const FLOAT32 = 7;
const FLOAT64 = 8;

/**
 * @param {object} msg a decoded PointCloud2
 * @param {number} maxPoints upper bound on returned points
 * @returns {{xyz: Float32Array, n: number, total: number}}
 */
export function cloudXYZ(msg, maxPoints) {
  const f = Object.fromEntries(msg.fields.map((x) => [x.name, x]));
  if (!f.x || !f.y || !f.z) throw new Error("PointCloud2 has no x, y, z fields");
  const step = msg.point_step;
  const data = msg.data;
  const total = step > 0 ? Math.min(msg.width * msg.height, Math.floor(data.byteLength / step)) : 0;
  const k = Math.max(1, Math.ceil(total / maxPoints));
  const n = Math.floor((total + k - 1) / k);
  const xyz = new Float32Array(n * 3);
  const allF32 = [f.x, f.y, f.z].every((a) => a.datatype === FLOAT32);
  if (allF32 && !msg.is_bigendian && step % 4 === 0 && data.byteOffset % 4 === 0 &&
      f.x.offset % 4 === 0 && f.y.offset % 4 === 0 && f.z.offset % 4 === 0) {
    // Fast path: one aligned Float32Array view over the whole cloud, strided reads.
    const v = new Float32Array(data.buffer, data.byteOffset, Math.floor(data.byteLength / 4));
    const s = step / 4, ox = f.x.offset / 4, oy = f.y.offset / 4, oz = f.z.offset / 4;
    for (let i = 0, j = 0; j < n; i += k, j++) {
      xyz[3 * j] = v[i * s + ox];
      xyz[3 * j + 1] = v[i * s + oy];
      xyz[3 * j + 2] = v[i * s + oz];
    }
    return { xyz, n, total };
  }
  const dv = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const le = !msg.is_bigendian;
  const get = (fl, at) => (fl.datatype === FLOAT64 ? dv.getFloat64(at + fl.offset, le) : dv.getFloat32(at + fl.offset, le));
  for (let i = 0, j = 0; j < n; i += k, j++) {
    xyz[3 * j] = get(f.x, i * step);
    xyz[3 * j + 1] = get(f.y, i * step);
    xyz[3 * j + 2] = get(f.z, i * step);
  }
  return { xyz, n, total };
}
