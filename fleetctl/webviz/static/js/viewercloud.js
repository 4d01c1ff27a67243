// Decode a fleetctl_msgs/msg/ViewerCloud (the viewer encoding of a PointCloud2 that robots
// send on <cloud topic>/viewer; fleetctl/client/viewercloud.py encodes it) into the arrays
// three.js draws. A pure module: no DOM, no three.js.
//
// The message, as the page's generic reader returns it (fb/reader.js):
//   resolution_m, origin_x, origin_y, origin_z: numbers (float32 on the wire), metres;
//   xyz: Int16Array of 3n voxel indices, PLANAR (all x, then all y, then all z), sorted by
//        (x, y, z); a point is origin + (index + 0.5) * resolution_m;
//   rgb: Uint8Array, empty or 3n colours, PLANAR (all r, then all g, then all b).
// Frames arrive deflate-compressed; connection.js inflates them before the reader runs.

export const VIEWER_CLOUD_TYPE = "fleetctl_msgs/msg/ViewerCloud";

/** The message does not hold a well-formed viewer cloud (the text says which field). */
export class ViewerCloudError extends Error {}

/**
 * Positions (and colours, when sent) of a ViewerCloud, interleaved as three.js wants them.
 *
 * @param {object} msg a decoded ViewerCloud
 * @param {number} [maxPoints=Infinity] upper bound on returned points: every k-th voxel is
 *   kept beyond it (as views/cloudpoints.js decimates full clouds)
 * @returns {{xyz: Float32Array, colors: Float32Array|null, n: number, total: number,
 *   resolution: number}} xyz: 3n metres (voxel centres, float32); colors: 3n in [0, 1] or
 *   null when the robot sent none; n: points returned; total: voxels in the message
 * @throws {ViewerCloudError} on arrays of the wrong length or a bad resolution/origin
 */
export function viewerCloudXYZ(msg, maxPoints = Infinity) {
  const idx = msg.xyz;
  const rgb = msg.rgb ?? new Uint8Array(0);
  const res = Number(msg.resolution_m);
  const origin = [Number(msg.origin_x), Number(msg.origin_y), Number(msg.origin_z)];
  if (!ArrayBuffer.isView(idx) && !Array.isArray(idx)) throw new ViewerCloudError("xyz is not an array");
  if (idx.length % 3 !== 0) {
    throw new ViewerCloudError(`xyz has ${idx.length} values, not a multiple of 3`);
  }
  const total = idx.length / 3;
  if (rgb.length !== 0 && rgb.length !== idx.length) {
    throw new ViewerCloudError(`rgb has ${rgb.length} values for ${total} points (3 per point or none)`);
  }
  if (!(res > 0) || !Number.isFinite(res)) throw new ViewerCloudError(`resolution_m is ${res}`);
  if (!origin.every(Number.isFinite)) throw new ViewerCloudError("origin is not finite");
  const k = Math.max(1, Math.ceil(total / Math.max(1, maxPoints)));
  const n = Math.ceil(total / k);
  const xyz = new Float32Array(n * 3);
  // Centre of voxel 0 on each axis: origin + 0.5 * res (one add per coordinate below).
  const cx = origin[0] + 0.5 * res, cy = origin[1] + 0.5 * res, cz = origin[2] + 0.5 * res;
  for (let i = 0, j = 0; j < n; i += k, j++) {
    xyz[3 * j] = cx + idx[i] * res;
    xyz[3 * j + 1] = cy + idx[total + i] * res;
    xyz[3 * j + 2] = cz + idx[2 * total + i] * res;
  }
  let colors = null;
  if (rgb.length !== 0) {
    colors = new Float32Array(n * 3);
    for (let i = 0, j = 0; j < n; i += k, j++) {
      colors[3 * j] = rgb[i] / 255;
      colors[3 * j + 1] = rgb[total + i] / 255;
      colors[3 * j + 2] = rgb[2 * total + i] / 255;
    }
  }
  return { xyz, colors, n, total, resolution: res };
}
