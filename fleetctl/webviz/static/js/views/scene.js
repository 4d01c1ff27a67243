// The robot's 3D scene: one three.js scene in a fixed frame (map, else odom, else the root
// of the robot's TF tree, or the user's choice), drawing scan, clouds (full PointCloud2 and
// ViewerCloud), the map, odometry with its trail, the localization pose, the plan and
// markers, each placed through the robot's TF tree (../tf.js) with the newest transforms.
// A message whose frame is not connected to the fixed frame is hidden and listed on the
// page ("/r1/scan: frame base_scan not connected to map (...)"), never drawn in the wrong
// place. The frame tree is listed beside the scene, with axes per frame on request.

import { DrawPacer } from "../drawpacer.js";
import { TfTree, normalizeFrame } from "../tf.js";
import { viewerCloudXYZ } from "../viewercloud.js";
import * as O from "./sceneobjects.js";

const MAX_MARKERS = 2000; // markers kept (oldest evicted, counted), as the map panel
const MAX_TRAIL = 2000; // odometry trail points
const MAX_PROBLEMS = 50;
const POSE_COLOR = 0xffca28;
const ODOM_COLOR = 0x66bb6a;
const PLAN_COLOR = 0x29b6f6;
const BASE_FRAMES = ["base_link", "base_footprint"]; // what the camera follows, if present

const TYPES = {
  TF: "tf2_msgs/msg/TFMessage",
  SCAN: "sensor_msgs/msg/LaserScan",
  CLOUD: "sensor_msgs/msg/PointCloud2",
  VIEWER_CLOUD: "fleetctl_msgs/msg/ViewerCloud",
  GRID: "nav_msgs/msg/OccupancyGrid",
  ODOM: "nav_msgs/msg/Odometry",
  POSE: "geometry_msgs/msg/PoseWithCovarianceStamped",
  PATH: "nav_msgs/msg/Path",
  MARKER: "visualization_msgs/msg/Marker",
  MARKERS: "visualization_msgs/msg/MarkerArray",
};
export const SCENE_TYPES = new Set(Object.values(TYPES));

function webglAvailable() {
  try {
    const c = document.createElement("canvas");
    return !!(c.getContext("webgl2") || c.getContext("webgl"));
  } catch {
    return false;
  }
}

/** The part of a TF lookup's reason after "no path from A to B: ". */
function why(reason) {
  const i = reason.indexOf(": ");
  return i >= 0 ? reason.slice(i + 2) : reason;
}

export class SceneView {
  /**
   * @param {{canvas: HTMLCanvasElement, tree: HTMLElement, problems: HTMLElement,
   *          fixedLabel: HTMLElement, frameSelect: HTMLSelectElement, axes: HTMLInputElement}} els
   */
  constructor(els, vendorBase = "vendor/") {
    this.els = els;
    this.canvas = els.canvas;
    this.tf = new TfTree();
    this.entries = new Map(); // key -> {topic, frame, group, content}
    this.retired = []; // replaced contents, disposed after the next draw (retire())
    this.draws = 0; // draws so far: an entry set since the last one was never drawn
    this.pacer = new DrawPacer(); // draws take at most half the main thread (drawpacer.js)
    this.markerKeys = new Set(); // insertion order = age, for eviction
    this.trails = new Map(); // odometry topic -> {frame, points}
    this.backlog = new Map(); // key -> [meta, msg] that arrived before three.js loaded
    this.axes = new Map(); // frame -> AxesHelper
    this.chosenFrame = null;
    this.fixed = { frame: null, why: "nothing received" };
    this.problems = []; // strings shown under the scene, also read by tests
    this.notes = []; // problems that are not about TF (a type not drawn, a bad message)
    this.stats = { messages: 0, errors: 0, markersEvicted: 0, hidden: 0, drawn: 0 };
    this.dirty = true;
    this.tfVersion = -1;
    this.azimuth = -2.4;
    this.rangeM = 11;
    this.mode = "pending";
    els.axes.addEventListener("change", () => (this.dirty = true));
    els.frameSelect.addEventListener("change", () => {
      this.chosenFrame = els.frameSelect.value || null;
      this.clearTrails();
      this.dirty = true;
    });
    this.ready = this.init(vendorBase);
  }

  async init(vendorBase) {
    if (webglAvailable()) {
      try {
        this.THREE = await import(new URL(`${vendorBase}three/three.module.js`, document.baseURI).href);
        this.initThree();
        this.mode = "webgl";
      } catch (err) {
        this.reason = `three.js unavailable (${err.message}): the scene cannot be drawn`;
      }
    } else {
      this.reason = "WebGL unavailable: the scene cannot be drawn (the frame tree is still listed)";
    }
    if (this.mode !== "webgl") this.mode = "none";
    this.canvas.dataset.mode = this.mode;
    if (this.reason) this.canvas.title = this.reason;
    for (const [meta, msg] of this.backlog.values()) this.update(meta, msg);
    this.backlog.clear();
  }

  initThree() {
    const THREE = this.THREE;
    this.renderer = new THREE.WebGLRenderer({ canvas: this.canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setClearColor(0x101418);
    this.renderer.setSize(this.canvas.width, this.canvas.height, false);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(50, this.canvas.width / this.canvas.height, 0.05, 1000);
    this.camera.up.set(0, 0, 1);
    this.target = new THREE.Vector3();
    this.scene.add(new THREE.GridHelper(20, 20, 0x2a3540, 0x2a3540).rotateX(Math.PI / 2));
    let drag = null;
    this.canvas.addEventListener("pointerdown", (e) => (drag = e.clientX));
    this.canvas.addEventListener("pointerup", () => (drag = null));
    this.canvas.addEventListener("pointermove", (e) => {
      if (drag === null) return;
      this.azimuth += (e.clientX - drag) * 0.01;
      drag = e.clientX;
      this.dirty = true;
    });
    this.canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.rangeM = Math.min(200, Math.max(1, this.rangeM * (e.deltaY < 0 ? 1 / 1.2 : 1.2)));
      this.dirty = true;
    });
  }

  /** Another robot's page: forget its tree and everything drawn. */
  reset() {
    for (const key of [...this.entries.keys()]) this.remove(key);
    for (const a of this.axes.values()) this.scene?.remove(a);
    this.axes.clear();
    this.markerKeys.clear();
    this.trails.clear();
    this.backlog.clear();
    this.tf = new TfTree();
    this.chosenFrame = null;
    this.problems = [];
    this.notes = [];
    this.dirty = true;
    this.renderLists();
  }

  /** Take one message; returns false for types the scene does not draw. */
  update(meta, msg) {
    if (!SCENE_TYPES.has(meta.type)) return false;
    this.stats.messages++;
    if (meta.type === TYPES.TF) {
      this.tf.update(msg, meta.topic.endsWith("/tf_static"));
      return true;
    }
    if (this.mode === "pending") {
      this.backlog.set(`${meta.topic} ${meta.type}`, [meta, msg]);
      return true;
    }
    if (this.mode !== "webgl") return true;
    try {
      this.draw(meta, msg);
    } catch (err) {
      this.stats.errors++;
      this.note(`${meta.topic}: cannot draw ${meta.type}: ${err.message}`);
    }
    this.dirty = true;
    return true;
  }

  draw(meta, msg) {
    const { THREE } = this;
    const t = meta.topic;
    const frame = msg.header?.frame_id;
    switch (meta.type) {
      case TYPES.SCAN: return this.set(t, t, frame, O.scanObject(THREE, msg));
      case TYPES.CLOUD: return this.set(t, t, frame, O.cloudObject(THREE, msg));
      case TYPES.VIEWER_CLOUD: return this.set(t, t, frame, O.viewerCloudObject(THREE, viewerCloudXYZ(msg, O.MAX_CLOUD_POINTS)));
      case TYPES.GRID: return this.set(t, t, frame, O.gridObject(THREE, msg));
      case TYPES.POSE: return this.set(t, t, frame, O.poseObject(THREE, msg.pose.pose, POSE_COLOR));
      case TYPES.PATH: return this.set(t, t, frame, O.lineObject(THREE, msg.poses.map((p) => p.pose.position), PLAN_COLOR));
      case TYPES.ODOM: return this.odometry(t, frame, msg.pose.pose);
      case TYPES.MARKER:
      case TYPES.MARKERS:
        for (const m of msg.markers ?? [msg]) this.marker(t, m);
        return undefined;
      default:
        return undefined;
    }
  }

  /** Put `content` (in `frame`) under `key`, replacing what was there. */
  set(key, topic, frame, content) {
    if (!content) return this.remove(key); // e.g. a grid whose size does not match its data
    const old = this.entries.get(key);
    if (old) {
      old.group.remove(old.content);
      this.retire(old);
    }
    let group = old?.group;
    if (!group) {
      group = new this.THREE.Group();
      group.matrixAutoUpdate = false;
      this.scene.add(group);
    }
    group.add(content);
    this.entries.set(key, { topic, frame: normalizeFrame(frame), group, content, setAt: this.draws });
    return undefined;
  }

  remove(key) {
    const e = this.entries.get(key);
    if (!e) return;
    this.scene?.remove(e.group);
    this.retire(e);
    this.entries.delete(key);
    this.markerKeys.delete(key);
  }

  /**
   * Dispose an entry's content after the next draw, not now. three.js deletes a shader
   * program when the last material using it is disposed, so disposing the old scan before
   * its successor was drawn made the successor compile and link the same program again:
   * 12.5 program links a second for one simulated robot, each a synchronous wait on the GPU
   * process (docs/webviz.md, "The 3D scene's cost per message"). Content set since the last
   * draw was never drawn, holds no program, and goes at once (paced draws let several
   * scans replace each other between two draws).
   */
  retire(entry) {
    if (entry.setAt === this.draws) O.dispose(entry.content);
    else this.retired.push(entry.content);
    this.dirty = true;
  }

  disposeRetired() {
    for (const c of this.retired) O.dispose(c);
    this.retired.length = 0;
  }

  odometry(topic, frame, pose) {
    this.set(topic, topic, frame, O.poseObject(this.THREE, pose, ODOM_COLOR));
    // The trail lives in the odometry's own frame (continuous there), placed through TF.
    let trail = this.trails.get(topic);
    if (!trail || trail.frame !== frame) trail = { frame, points: [] };
    const p = pose.position;
    const last = trail.points[trail.points.length - 1];
    if (!last || Math.hypot(last.x - p.x, last.y - p.y) > 0.05) trail.points.push({ x: p.x, y: p.y, z: p.z });
    if (trail.points.length > MAX_TRAIL) trail.points.shift();
    this.trails.set(topic, trail);
    const segments = O.pathSegments(trail.points);
    if (segments.length) this.set(`${topic} trail`, topic, frame, O.lineObject(this.THREE, segments, ODOM_COLOR, true));
  }

  clearTrails() {
    for (const t of this.trails.keys()) this.remove(`${t} trail`);
    this.trails.clear();
  }

  marker(topic, m) {
    const key = `${topic} ${m.ns}/${m.id}`;
    if (m.action === 3) { // DELETEALL (of this topic)
      for (const k of [...this.markerKeys]) if (this.entries.get(k)?.topic === topic) this.remove(k);
      return;
    }
    this.remove(key);
    if (m.action === 2) return; // DELETE
    const obj = O.markerObject(this.THREE, m);
    if (!obj) return this.note(`${topic}: marker ${m.ns}/${m.id} type ${m.type} (mesh) is not drawn here`);
    this.set(key, topic, m.header.frame_id, obj);
    this.markerKeys.add(key);
    if (this.markerKeys.size > MAX_MARKERS) {
      this.remove(this.markerKeys.values().next().value);
      this.stats.markersEvicted++;
    }
  }

  /** A line for the problems list that is not about TF (kept until reset, bounded). */
  note(text) {
    if (this.notes.includes(text)) return;
    this.notes.push(text);
    if (this.notes.length > 10) this.notes.shift();
  }

  /** The fixed frame: the user's, else TF's choice; with no TF, the messages' own frames. */
  chooseFixed() {
    if (this.tf.known.size) return this.tf.fixedFrame(this.chosenFrame);
    const frames = [...this.entries.values()].map((e) => e.frame).filter(Boolean);
    for (const f of ["map", "odom"]) if (frames.includes(f)) return { frame: f, why: `no TF received: ${f}` };
    return frames.length ? { frame: frames[0], why: "no TF received: the first message's frame" } : { frame: null, why: "no TF received" };
  }

  /** Place every entry through TF; hide (and list) what is not connected. */
  place() {
    const fixed = (this.fixed = this.chooseFixed());
    const cache = new Map();
    const lookup = (frame) => {
      if (!cache.has(frame)) cache.set(frame, this.tf.lookup(fixed.frame ?? "", frame));
      return cache.get(frame);
    };
    const problems = new Map();
    let hidden = 0;
    for (const e of this.entries.values()) {
      const r = lookup(e.frame);
      e.group.visible = r.ok;
      if (r.ok) {
        e.group.matrix.fromArray(r.matrix);
        e.group.matrixWorldNeedsUpdate = true;
        continue;
      }
      hidden++;
      const text = `${e.topic}: frame ${e.frame || "(empty)"} not connected to ${fixed.frame ?? "a fixed frame"} (${why(r.reason)})`;
      problems.set(`${e.topic} ${e.frame}`, text);
    }
    this.stats.hidden = hidden;
    this.stats.drawn = this.entries.size - hidden;
    this.problems = [...problems.values(), ...this.notes, ...this.tf.problems].slice(0, MAX_PROBLEMS);
    this.placeAxes(lookup);
    const base = BASE_FRAMES.map(lookup).find((r) => r.ok);
    if (base) this.target.set(base.matrix[12], base.matrix[13], base.matrix[14]);
    else this.target.set(0, 0, 0);
  }

  placeAxes(lookup) {
    const on = this.els.axes.checked;
    for (const f of on ? this.tf.known : []) {
      if (!this.axes.has(f)) {
        const a = new this.THREE.AxesHelper(0.4);
        a.matrixAutoUpdate = false;
        this.axes.set(f, a);
        this.scene.add(a);
      }
    }
    for (const [f, a] of this.axes) {
      const r = on && this.tf.known.has(f) ? lookup(f) : { ok: false };
      a.visible = r.ok;
      if (r.ok) a.matrix.fromArray(r.matrix);
    }
  }

  /** Draw what changed, at most as often as the pacer allows (*nowMs*: the frame's time). */
  render(nowMs = performance.now()) {
    if (this.mode !== "webgl") return this.disposeRetired();
    const due = this.pacer.due(nowMs); // every frame: it learns the last draw's cost here
    if (!this.dirty && this.tfVersion === this.tf.version) return;
    if (this.canvas.offsetParent === null) return this.disposeRetired(); // hidden: draw when shown
    if (!due) return this.pacer.defer();
    this.dirty = false;
    this.tfVersion = this.tf.version;
    this.place();
    const el = 0.9; // camera elevation (rad)
    this.camera.position.set(
      this.target.x + this.rangeM * Math.cos(el) * Math.cos(this.azimuth),
      this.target.y + this.rangeM * Math.cos(el) * Math.sin(this.azimuth),
      this.target.z + this.rangeM * Math.sin(el),
    );
    this.camera.lookAt(this.target);
    this.renderer.render(this.scene, this.camera);
    this.draws++;
    this.pacer.drew(nowMs);
    this.disposeRetired(); // their programs now have the new contents' materials as users
    this.canvas.dataset.drawn = String(this.stats.drawn);
    this.canvas.dataset.draws = String(this.draws);
    this.canvas.dataset.deferred = String(this.pacer.deferred);
    this.canvas.dataset.fixed = this.fixed.frame ?? "";
  }

  /** The tree list, the fixed frame and the problems (once a second: they are text). */
  renderLists(nowMs = Date.now()) {
    if (this.mode !== "webgl") {
      // Nothing is drawn; the tree and the reason are still worth showing.
      this.fixed = this.chooseFixed();
      this.problems = [this.reason ?? "loading three.js", ...this.tf.problems];
    }
    const { tree, problems, fixedLabel, frameSelect } = this.els;
    const fixed = this.fixed;
    fixedLabel.textContent = fixed.frame ? `Fixed frame: ${fixed.frame} (${fixed.why})` : `No fixed frame yet (${fixed.why})`;
    const rows = this.tf.rows(nowMs);
    tree.replaceChildren(...rows.map((r) => {
      const li = document.createElement("li");
      li.style.paddingLeft = `${r.depth * 14}px`;
      li.dataset.frame = r.frame;
      const age = r.parent === null ? "root" : r.isStatic ? "static" : `${(r.ageMs / 1000).toFixed(1)} s ago`;
      li.append(r.frame, Object.assign(document.createElement("span"), { className: "muted", textContent: ` ${age}` }));
      return li;
    }));
    if (!rows.length) tree.replaceChildren(Object.assign(document.createElement("li"), { className: "muted", textContent: "no TF received" }));
    const want = ["", ...rows.map((r) => r.frame)];
    // Compared as JSON: with no TF yet, [] and [""] joined alike and the select stayed
    // empty (no "auto" choice) until a transform arrived.
    if (JSON.stringify([...frameSelect.options].map((o) => o.value)) !== JSON.stringify(want)) {
      frameSelect.replaceChildren(...want.map((f) => new Option(f || "auto (map, odom, root)", f)));
      frameSelect.value = this.chosenFrame ?? "";
    }
    problems.replaceChildren(...this.problems.map((p) => Object.assign(document.createElement("li"), { textContent: p })));
    problems.hidden = this.problems.length === 0;
  }

  /**
   * Where an entry is drawn, for tests and debugging.
   * @returns {{visible: boolean, frame: string, fixed: string|null, matrixWorld: number[]}|null}
   */
  placement(key) {
    const e = this.entries.get(key);
    if (!e) return null;
    this.place();
    this.scene.updateMatrixWorld(true);
    return { visible: e.group.visible, frame: e.frame, fixed: this.fixed.frame, matrixWorld: [...e.group.matrixWorld.elements], points: e.content.userData.points ?? null };
  }
}
