// 3D point cloud panel: three.js (Debian libjs-three, served under /vendor/three/) with
// WebGL; falls back to a 2D top-down canvas projection when WebGL or three.js is missing.

import { cloudXYZ } from "./cloudpoints.js";

const MAX_POINTS = 60000; // decimation bound per cloud

function webglAvailable() {
  try {
    const c = document.createElement("canvas");
    return !!(c.getContext("webgl2") || c.getContext("webgl"));
  } catch {
    return false;
  }
}

export class CloudView {
  constructor(canvas, vendorBase = "vendor/") {
    this.canvas = canvas;
    this.latest = null;
    this.mode = "pending";
    this.azimuth = -2.4;
    this.ready = this.init(vendorBase);
  }

  async init(vendorBase) {
    if (webglAvailable()) {
      try {
        this.THREE = await import(new URL(`${vendorBase}three/three.module.js`, document.baseURI).href);
        this.initThree();
        this.mode = "webgl";
      } catch (err) {
        this.reason = `three.js unavailable (${err.message}); drawing a 2D projection`;
      }
    } else {
      this.reason = "WebGL unavailable; drawing a 2D projection";
    }
    if (this.mode !== "webgl") this.mode = "canvas";
    this.canvas.dataset.mode = this.mode;
    if (this.reason) this.canvas.title = this.reason;
  }

  initThree() {
    const THREE = this.THREE;
    this.renderer = new THREE.WebGLRenderer({ canvas: this.canvas, antialias: false, preserveDrawingBuffer: true });
    this.renderer.setClearColor(0x101418);
    this.renderer.setSize(this.canvas.width, this.canvas.height, false);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(55, this.canvas.width / this.canvas.height, 0.1, 500);
    this.camera.up.set(0, 0, 1);
    // One WebGL buffer each for positions and colours, MAX_POINTS long, written in place for
    // every cloud. A new BufferAttribute per cloud made two new WebGL buffers (720 KB each
    // at 60,000 points, 5 clouds a second) that three.js never deletes: only the garbage
    // collector taking their wrappers freed them, so the GPU process held whatever the
    // collector had not reached yet (docs/webviz.md, "The page left open").
    this.positions = new THREE.BufferAttribute(new Float32Array(MAX_POINTS * 3), 3).setUsage(THREE.DynamicDrawUsage);
    this.colors = new THREE.BufferAttribute(new Float32Array(MAX_POINTS * 3), 3).setUsage(THREE.DynamicDrawUsage);
    this.geometry = new THREE.BufferGeometry();
    this.geometry.setAttribute("position", this.positions);
    this.geometry.setAttribute("color", this.colors);
    this.geometry.setDrawRange(0, 0);
    this.material = new THREE.PointsMaterial({ size: 0.08, vertexColors: THREE.VertexColors });
    const points = new THREE.Points(this.geometry, this.material);
    // Its bounding sphere would be computed over all MAX_POINTS, stale ones included.
    points.frustumCulled = false;
    this.scene.add(points);
    this.scene.add(new THREE.GridHelper(20, 20, 0x2a3540, 0x2a3540).rotateX(Math.PI / 2));
    this.placeCamera();
    let dragX = null;
    this.canvas.addEventListener("pointerdown", (e) => (dragX = e.clientX));
    this.canvas.addEventListener("pointerup", () => (dragX = null));
    this.canvas.addEventListener("pointermove", (e) => {
      if (dragX === null) return;
      this.azimuth += (e.clientX - dragX) * 0.01;
      dragX = e.clientX;
      this.placeCamera();
      this.renderer.render(this.scene, this.camera);
    });
  }

  placeCamera() {
    this.camera.position.set(9 * Math.cos(this.azimuth), 9 * Math.sin(this.azimuth), 6);
    this.camera.lookAt(0, 0, 0);
  }

  update(msg) {
    this.latest = msg;
  }

  /** Another robot's page: blank what the last one showed. */
  reset() {
    this.latest = null;
    delete this.canvas.dataset.points;
    if (this.mode === "webgl") this.drawThree(new Float32Array(0), 0);
    else if (this.mode === "canvas") this.drawCanvas(new Float32Array(0), 0);
  }

  render() {
    const msg = this.latest;
    if (!msg || this.mode === "pending") return;
    this.latest = null;
    const { xyz, n, total } = cloudXYZ(msg, MAX_POINTS);
    this.canvas.dataset.points = String(n);
    this.canvas.dataset.total = String(total);
    if (this.mode === "webgl") this.drawThree(xyz, n);
    else this.drawCanvas(xyz, n);
  }

  drawThree(xyz, n) {
    n = Math.min(n, MAX_POINTS);
    const colors = this.colors.array;
    for (let i = 0; i < n; i++) {
      const t = Math.max(0, Math.min(1, (xyz[3 * i + 2] + 0.5) / 3)); // colour by height
      colors[3 * i] = 0.3 + 0.7 * t;
      colors[3 * i + 1] = 0.9 - 0.5 * t;
      colors[3 * i + 2] = 1.0 - 0.8 * t;
    }
    this.positions.array.set(xyz.subarray(0, 3 * n));
    if (n > 0) {
      // Only this cloud's part goes to the GPU (three.js refuses an empty range).
      for (const a of [this.positions, this.colors]) {
        a.updateRange = { offset: 0, count: 3 * n };
        a.needsUpdate = true;
      }
    }
    this.geometry.setDrawRange(0, n);
    this.renderer.render(this.scene, this.camera);
  }

  drawCanvas(xyz, n) {
    const ctx = this.canvas.getContext("2d");
    const w = this.canvas.width, h = this.canvas.height;
    ctx.fillStyle = "#101418";
    ctx.fillRect(0, 0, w, h);
    const scale = Math.min(w, h) / 20; // px per m: a 20 m square
    ctx.fillStyle = "#7fe0a0";
    for (let i = 0; i < n; i++) {
      ctx.fillRect(w / 2 - xyz[3 * i + 1] * scale, h / 2 - xyz[3 * i] * scale, 2, 2);
    }
  }
}
