// three.js objects for the 3D scene, each in its message's own frame (the scene places
// them through TF): laser scans, point clouds, occupancy grids, poses, lines and markers.
// `THREE` is passed in (Debian's libjs-three r111, loaded at run time).

import { cloudXYZ } from "./cloudpoints.js";

export const MAX_CLOUD_POINTS = 60000; // decimation bound per cloud, as the cloud panel
const MAX_TEXTURE_PX = 4096; // grids wider than this are sampled down (WebGL texture limits)

const SCAN_COLOR = 0xff9d2e;

function pointsObject(THREE, xyz, colors, { color = 0xffffff, sizePx = 3 } = {}) {
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
  const material = new THREE.PointsMaterial({ size: sizePx, sizeAttenuation: false, color: colors ? 0xffffff : color });
  if (colors) {
    geometry.setAttribute("color", new THREE.BufferAttribute(colors, 3));
    material.vertexColors = THREE.VertexColors;
  }
  geometry.computeBoundingSphere();
  return new THREE.Points(geometry, material);
}

/** sensor_msgs/msg/LaserScan: its valid ranges as points in the scanner's frame (z = 0). */
export function scanObject(THREE, msg) {
  const r = msg.ranges;
  const xyz = new Float32Array(r.length * 3);
  let n = 0;
  for (let i = 0; i < r.length; i++) {
    if (!(r[i] >= msg.range_min && r[i] <= msg.range_max)) continue;
    const a = msg.angle_min + i * msg.angle_increment;
    xyz[3 * n] = r[i] * Math.cos(a);
    xyz[3 * n + 1] = r[i] * Math.sin(a);
    n++;
  }
  const obj = pointsObject(THREE, xyz.subarray(0, 3 * n), null, { color: SCAN_COLOR, sizePx: 4 });
  obj.userData.points = n;
  return obj;
}

/** Colour by height, as the cloud panel does. */
function heightColors(xyz, n) {
  const colors = new Float32Array(n * 3);
  for (let i = 0; i < n; i++) {
    const t = Math.max(0, Math.min(1, (xyz[3 * i + 2] + 0.5) / 3));
    colors[3 * i] = 0.3 + 0.7 * t;
    colors[3 * i + 1] = 0.9 - 0.5 * t;
    colors[3 * i + 2] = 1.0 - 0.8 * t;
  }
  return colors;
}

/** sensor_msgs/msg/PointCloud2 (decimated to MAX_CLOUD_POINTS). */
export function cloudObject(THREE, msg) {
  const { xyz, n } = cloudXYZ(msg, MAX_CLOUD_POINTS);
  const obj = pointsObject(THREE, xyz, heightColors(xyz, n), { sizePx: 2 });
  obj.userData.points = n;
  return obj;
}

/** A decoded fleetctl_msgs/msg/ViewerCloud ({xyz, colors, n} from viewercloud.js). */
export function viewerCloudObject(THREE, { xyz, colors, n }) {
  const obj = pointsObject(THREE, xyz, colors ?? heightColors(xyz, n), { sizePx: 2 });
  obj.userData.points = n;
  return obj;
}

function placePose(obj, pose) {
  const p = pose.position, q = pose.orientation;
  obj.position.set(p.x, p.y, p.z);
  if (Math.hypot(q.x, q.y, q.z, q.w) > 0) obj.quaternion.set(q.x, q.y, q.z, q.w).normalize();
  return obj;
}

/** nav_msgs/msg/OccupancyGrid as a textured plane (unknown cells transparent). */
export function gridObject(THREE, msg) {
  const { width, height, resolution, origin } = msg.info;
  if (!(width > 0 && height > 0 && resolution > 0) || width * height > msg.data.length) return null;
  const k = Math.ceil(Math.max(width, height) / MAX_TEXTURE_PX);
  const w = Math.ceil(width / k), h = Math.ceil(height / k);
  const rgba = new Uint8Array(w * h * 4);
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      const v = msg.data[y * k * width + x * k];
      const o = 4 * (y * w + x);
      const c = v < 0 ? 90 : 235 - Math.round((Math.min(v, 100) / 100) * 220);
      rgba[o] = rgba[o + 1] = rgba[o + 2] = c;
      rgba[o + 3] = v < 0 ? 60 : 255;
    }
  }
  // Row 0 of the grid is its min-y edge, which is the texture's v = 0: no flip needed.
  const texture = new THREE.DataTexture(rgba, w, h, THREE.RGBAFormat);
  texture.magFilter = THREE.NearestFilter;
  texture.needsUpdate = true;
  const sx = width * resolution, sy = height * resolution;
  const geometry = new THREE.PlaneBufferGeometry(sx, sy);
  geometry.translate(sx / 2, sy / 2, -0.01); // the plane's corner at the grid origin, just below z = 0
  // The floor: drawn first and without depth, so transparent things above it (text,
  // unknown cells) blend with it instead of punching holes to the background.
  const material = new THREE.MeshBasicMaterial({ map: texture, transparent: true, side: THREE.DoubleSide, depthWrite: false });
  const mesh = new THREE.Mesh(geometry, material);
  mesh.renderOrder = -1;
  mesh.userData.cells = width * height;
  return placePose(mesh, origin);
}

/** An arrow along +x of `pose` (odometry, localization pose). */
export function poseObject(THREE, pose, color, lengthM = 0.8) {
  const arrow = new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(0, 0, 0), lengthM, color, 0.3 * lengthM, 0.2 * lengthM);
  return placePose(arrow, pose);
}

/** A polyline through points {x, y, z}. */
/**
 * A driven path as line-segment pairs, with no segment across a jump: two points more than
 * *jumpM* apart (a relocalization, or the robot's data missing while it drove on) were
 * joined by a straight line the robot never drove, across the room.
 * @param {{x: number, y: number, z?: number}[]} points
 * @returns {{x: number, y: number, z?: number}[]} pairs: [a0, b0, a1, b1, ...]
 */
export function pathSegments(points, jumpM = 1.0) {
  const out = [];
  for (let i = 1; i < points.length; i++) {
    const a = points[i - 1], b = points[i];
    if (Math.hypot(b.x - a.x, b.y - a.y, (b.z ?? 0) - (a.z ?? 0)) <= jumpM) out.push(a, b);
  }
  return out;
}

export function lineObject(THREE, points, color, segments = false) {
  const xyz = new Float32Array(points.length * 3);
  points.forEach((p, i) => xyz.set([p.x, p.y, p.z ?? 0], 3 * i));
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
  const material = new THREE.LineBasicMaterial({ color });
  return segments ? new THREE.LineSegments(geometry, material) : new THREE.Line(geometry, material);
}

const M = { ARROW: 0, CUBE: 1, SPHERE: 2, CYLINDER: 3, LINE_STRIP: 4, LINE_LIST: 5, CUBE_LIST: 6, SPHERE_LIST: 7, POINTS: 8, TEXT: 9, MESH: 10, TRIANGLES: 11 };

function markerColor(THREE, c) {
  return new THREE.Color(c.r, c.g, c.b);
}

function markerMaterial(THREE, m, Kind = THREE.MeshBasicMaterial) {
  const a = m.color.a > 0 ? m.color.a : 1;
  return new Kind({ color: markerColor(THREE, m.color), transparent: a < 1, opacity: a });
}

function solid(THREE, m, geometry) {
  return new THREE.Mesh(geometry, markerMaterial(THREE, m));
}

function listPoints(THREE, m) {
  const n = m.points.length;
  const xyz = new Float32Array(n * 3);
  m.points.forEach((p, i) => xyz.set([p.x, p.y, p.z], 3 * i));
  let colors = null;
  if (m.colors?.length === n) {
    colors = new Float32Array(n * 3);
    m.colors.forEach((c, i) => colors.set([c.r, c.g, c.b], 3 * i));
  }
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
  const material = new THREE.PointsMaterial({ size: Math.max(0.01, m.scale.x), color: colors ? 0xffffff : markerColor(THREE, m.color) });
  if (colors) {
    geometry.setAttribute("color", new THREE.BufferAttribute(colors, 3));
    material.vertexColors = THREE.VertexColors;
  }
  return new THREE.Points(geometry, material);
}

function textSprite(THREE, m) {
  const canvas = document.createElement("canvas");
  canvas.width = 256;
  canvas.height = 64;
  const ctx = canvas.getContext("2d");
  ctx.font = "40px sans-serif";
  ctx.textAlign = "center";
  ctx.textBaseline = "middle";
  ctx.fillStyle = `rgb(${m.color.r * 255},${m.color.g * 255},${m.color.b * 255})`;
  ctx.fillText(m.text, 128, 32, 250);
  const sprite = new THREE.Sprite(new THREE.SpriteMaterial({ map: new THREE.CanvasTexture(canvas), transparent: true, depthWrite: false }));
  const h = Math.max(0.05, m.scale.z);
  sprite.scale.set(4 * h, h, 1);
  return sprite;
}

function arrowMarker(THREE, m) {
  const color = markerColor(THREE, m.color);
  if (m.points.length >= 2) {
    // Points given: from the first to the second, in the marker's frame.
    const a = new THREE.Vector3(m.points[0].x, m.points[0].y, m.points[0].z);
    const b = new THREE.Vector3(m.points[1].x, m.points[1].y, m.points[1].z);
    const len = a.distanceTo(b);
    return new THREE.ArrowHelper(b.clone().sub(a).normalize(), a, len, color, Math.max(m.scale.z, 0.2 * len), Math.max(m.scale.y, 0.1 * len));
  }
  const len = Math.max(m.scale.x, 0.05);
  return new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(), len, color, 0.3 * len, Math.max(m.scale.y, 0.1 * len));
}

/**
 * A visualization_msgs/msg/Marker as a three.js object in the marker's frame, or null for
 * a type not drawn here (MESH_RESOURCE: the page cannot fetch robot meshes).
 */
export function markerObject(THREE, m) {
  const s = m.scale;
  let obj;
  switch (m.type) {
    case M.ARROW: obj = arrowMarker(THREE, m); break;
    case M.CUBE: obj = solid(THREE, m, new THREE.BoxBufferGeometry(s.x, s.y, s.z)); break;
    case M.SPHERE: obj = solid(THREE, m, new THREE.SphereBufferGeometry(0.5, 16, 12).scale(s.x, s.y, s.z)); break;
    case M.CYLINDER:
      // ROS cylinders stand on z; three.js's on y.
      obj = solid(THREE, m, new THREE.CylinderBufferGeometry(0.5, 0.5, 1, 20).rotateX(Math.PI / 2).scale(s.x, s.y, s.z));
      break;
    case M.LINE_STRIP: obj = lineObject(THREE, m.points, markerColor(THREE, m.color)); break;
    case M.LINE_LIST: obj = lineObject(THREE, m.points, markerColor(THREE, m.color), true); break;
    case M.CUBE_LIST:
    case M.SPHERE_LIST:
    case M.POINTS: obj = listPoints(THREE, m); break;
    case M.TEXT: obj = textSprite(THREE, m); break;
    case M.TRIANGLES: {
      const xyz = new Float32Array(m.points.length * 3);
      m.points.forEach((p, i) => xyz.set([p.x, p.y, p.z], 3 * i));
      const g = new THREE.BufferGeometry();
      g.setAttribute("position", new THREE.BufferAttribute(xyz, 3));
      obj = new THREE.Mesh(g, markerMaterial(THREE, m));
      obj.material.side = THREE.DoubleSide;
      break;
    }
    default:
      return null;
  }
  const wrapper = new THREE.Group();
  wrapper.add(obj);
  return placePose(wrapper, m.pose);
}

/** Free the GPU resources of an object tree. */
export function dispose(obj) {
  obj?.traverse?.((o) => {
    o.geometry?.dispose();
    const mats = Array.isArray(o.material) ? o.material : o.material ? [o.material] : [];
    for (const mat of mats) {
      mat.map?.dispose();
      mat.dispose();
    }
  });
}
