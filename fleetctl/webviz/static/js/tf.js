// One robot's TF tree, fed tf2_msgs/msg/TFMessage from /<robot>/tf and /<robot>/tf_static.
//
// Pure (no DOM, no three.js): tests run it under node. Each child frame keeps the latest
// transform from its parent (tf2 allows one parent per frame); there is NO interpolation
// and no lookup by time: a message is placed with the newest transforms the page has,
// which is what a viewer a few hundred ms behind the robot wants, but not what tf2's
// lookupTransform(stamp) would give for a fast-turning robot (docs/webviz.md, "TF").
//
// Matrices are 4x4, column-major in a Float64Array(16), the layout of three.js's
// Matrix4.elements, so a scene can use them with `matrix.fromArray(m)`.
//
// Bounded: at most MAX_FRAMES frames; transforms that would add more, create a cycle, or
// carry non-finite numbers are refused and counted in `stats`.

export const MAX_FRAMES = 1000;
const MAX_DEPTH = 256; // a chain longer than this is treated as broken (never in a sane robot)

/** Frame names are compared without a leading '/' (tf2 strips it too). */
export function normalizeFrame(name) {
  const s = String(name ?? "");
  return s.startsWith("/") ? s.replace(/^\/+/, "") : s;
}

/** 4x4 column-major matrix of a translation {x,y,z} and unit quaternion {x,y,z,w}. */
export function matrixOf(t, q) {
  let { x, y, z, w } = q;
  const n = Math.hypot(x, y, z, w);
  if (n > 0) {
    x /= n; y /= n; z /= n; w /= n;
  } else {
    x = y = z = 0; w = 1;
  }
  const m = new Float64Array(16);
  m[0] = 1 - 2 * (y * y + z * z);
  m[1] = 2 * (x * y + z * w);
  m[2] = 2 * (x * z - y * w);
  m[4] = 2 * (x * y - z * w);
  m[5] = 1 - 2 * (x * x + z * z);
  m[6] = 2 * (y * z + x * w);
  m[8] = 2 * (x * z + y * w);
  m[9] = 2 * (y * z - x * w);
  m[10] = 1 - 2 * (x * x + y * y);
  m[12] = t.x;
  m[13] = t.y;
  m[14] = t.z;
  m[15] = 1;
  return m;
}

export function identity() {
  const m = new Float64Array(16);
  m[0] = m[5] = m[10] = m[15] = 1;
  return m;
}

/** a * b (both column-major 4x4). */
export function multiply(a, b) {
  const out = new Float64Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = s;
    }
  }
  return out;
}

/** Inverse of a rigid transform (rotation + translation). */
export function invertRigid(m) {
  const out = new Float64Array(16);
  // Rotation part transposed.
  for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) out[c * 4 + r] = m[r * 4 + c];
  for (let r = 0; r < 3; r++) {
    out[12 + r] = -(out[r] * m[12] + out[4 + r] * m[13] + out[8 + r] * m[14]);
  }
  out[15] = 1;
  return out;
}

/** Apply a column-major matrix to a point [x, y, z]. */
export function transformPoint(m, p) {
  const [x, y, z] = p;
  return [m[0] * x + m[4] * y + m[8] * z + m[12], m[1] * x + m[5] * y + m[9] * z + m[13], m[2] * x + m[6] * y + m[10] * z + m[14]];
}

function finite(...xs) {
  return xs.every((x) => Number.isFinite(x));
}

export class TfTree {
  /** @param {{maxFrames?: number}} opts */
  constructor({ maxFrames = MAX_FRAMES } = {}) {
    this.maxFrames = maxFrames;
    this.edges = new Map(); // child -> {parent, matrix, isStatic, receivedMs}
    this.known = new Set(); // every frame named (parents without parents included)
    this.version = 0; // bumps on every accepted change: scenes re-place their objects
    this.stats = { accepted: 0, refusedCycle: 0, refusedFull: 0, refusedBad: 0, reparented: 0 };
    this.problems = []; // recent refusals, for the page (bounded)
  }

  /**
   * Feed one tf2_msgs/msg/TFMessage.
   * @param {{transforms: Array<object>}} msg as the generic reader decodes it
   * @param {boolean} isStatic from /tf_static
   * @param {number} nowMs browser clock, for the ages shown in the tree list
   * @returns {number} transforms accepted
   */
  update(msg, isStatic, nowMs = Date.now()) {
    let n = 0;
    for (const ts of msg.transforms ?? []) if (this.add(ts, isStatic, nowMs)) n++;
    if (n) this.version++;
    return n;
  }

  add(ts, isStatic, nowMs) {
    const parent = normalizeFrame(ts.header?.frame_id);
    const child = normalizeFrame(ts.child_frame_id);
    const t = ts.transform?.translation ?? {};
    const q = ts.transform?.rotation ?? {};
    if (!parent || !child || parent === child || !finite(t.x, t.y, t.z, q.x, q.y, q.z, q.w)) {
      return this.refuse("refusedBad", `bad transform ${parent || "?"} -> ${child || "?"} (empty, equal or non-finite)`);
    }
    const fresh = [parent, child].filter((f) => !this.known.has(f)).length;
    if (this.known.size + fresh > this.maxFrames) {
      return this.refuse("refusedFull", `more than ${this.maxFrames} frames: ${parent} -> ${child} ignored`);
    }
    if (this.isAncestor(child, parent)) {
      return this.refuse("refusedCycle", `${parent} -> ${child} would make a cycle (${child} is above ${parent})`);
    }
    const old = this.edges.get(child);
    if (old && old.parent !== parent) this.stats.reparented++; // tf2 also lets the newest parent win
    this.edges.set(child, { parent, matrix: matrixOf(t, q), isStatic, receivedMs: nowMs });
    this.known.add(parent);
    this.known.add(child);
    this.stats.accepted++;
    return true;
  }

  refuse(counter, text) {
    this.stats[counter]++;
    this.problems.push(text);
    if (this.problems.length > 20) this.problems.shift();
    return false;
  }

  /** True when `a` is `b` or one of b's ancestors. */
  isAncestor(a, b) {
    for (let f = b, d = 0; f !== undefined && d <= MAX_DEPTH; f = this.edges.get(f)?.parent, d++) {
      if (f === a) return true;
    }
    return false;
  }

  has(frame) {
    return this.known.has(normalizeFrame(frame));
  }

  /** [frame, its parent, ..., root] and the root's matrix chain (frame -> root). */
  chain(frame) {
    const frames = [frame];
    let m = identity();
    const toRoot = new Map([[frame, m]]); // ancestor -> T_ancestor_frame
    for (let f = frame, d = 0; d < MAX_DEPTH; d++) {
      const e = this.edges.get(f);
      if (!e) break;
      m = multiply(e.matrix, m);
      f = e.parent;
      frames.push(f);
      toRoot.set(f, m);
    }
    return { frames, toRoot, root: frames[frames.length - 1] };
  }

  /**
   * The transform taking points in `source` to `target` (T_target_source).
   * @returns {{ok: true, matrix: Float64Array} | {ok: false, reason: string}}
   */
  lookup(target, source) {
    target = normalizeFrame(target);
    source = normalizeFrame(source);
    const no = (why) => ({ ok: false, reason: `no path from ${source || "(empty)"} to ${target || "(empty)"}: ${why}` });
    if (!source) return no("the message has no frame_id");
    if (!target) return no("no fixed frame");
    if (source === target) return { ok: true, matrix: identity() };
    if (!this.known.has(source)) return no(`${source} is not in the TF tree`);
    if (!this.known.has(target)) return no(`${target} is not in the TF tree`);
    const s = this.chain(source);
    const t = this.chain(target);
    const common = s.frames.find((f) => t.toRoot.has(f));
    if (common === undefined) {
      // Say where the source's chain ends: that is the missing link an operator can fix.
      return no(`${s.root} has no parent` + (t.root !== target ? ` (${target} is under ${t.root})` : ""));
    }
    const m = multiply(invertRigid(t.toRoot.get(common)), s.toRoot.get(common));
    return { ok: true, matrix: m };
  }

  /** Frames without a parent, biggest subtree first. */
  roots() {
    const size = new Map();
    for (const f of this.known) {
      const r = this.chain(f).root;
      size.set(r, (size.get(r) ?? 0) + 1);
    }
    return [...size.entries()].sort((a, b) => b[1] - a[1] || a[0].localeCompare(b[0])).map(([r]) => r);
  }

  /**
   * The fixed frame a scene draws in: "map" if known, else "odom", else the root of the
   * biggest tree; `preferred` (the user's choice) wins when known.
   * @returns {{frame: string|null, why: string}}
   */
  fixedFrame(preferred = null) {
    if (preferred && this.has(preferred)) return { frame: normalizeFrame(preferred), why: "chosen" };
    if (this.known.has("map")) return { frame: "map", why: "map" };
    if (this.known.has("odom")) return { frame: "odom", why: "no map frame: odom" };
    const [root] = this.roots();
    return root ? { frame: root, why: "no map or odom frame: the tree's root" } : { frame: null, why: "no TF received" };
  }

  /**
   * The tree as nested rows for display, depth-first from each root.
   * @returns {Array<{frame: string, parent: string|null, depth: number, isStatic: boolean, ageMs: number}>}
   */
  rows(nowMs = Date.now()) {
    const children = new Map();
    for (const [child, e] of this.edges) {
      if (!children.has(e.parent)) children.set(e.parent, []);
      children.get(e.parent).push(child);
    }
    const out = [];
    const visit = (f, depth) => {
      const e = this.edges.get(f);
      out.push({ frame: f, parent: e?.parent ?? null, depth, isStatic: !!e?.isStatic, ageMs: e ? nowMs - e.receivedMs : NaN });
      for (const c of (children.get(f) ?? []).sort()) if (depth < MAX_DEPTH) visit(c, depth + 1);
    };
    for (const r of this.roots()) visit(r, 0);
    return out;
  }

  /** Forget every transform (another robot's page opens). */
  clear() {
    this.edges.clear();
    this.known.clear();
    this.version++;
  }
}
