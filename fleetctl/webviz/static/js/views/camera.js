// Camera panel: sensor_msgs/msg/CompressedImage -> Blob -> createImageBitmap -> canvas.
// At most one image decodes at a time; a frame arriving meanwhile replaces the waiting
// one (latest wins), so a slow phone never builds a backlog.

export class CameraView {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.busy = false;
    this.waiting = null;
    this.shown = 0;
    this.failed = 0;
    this.generation = 0; // bumped by reset(): a decode for the previous robot is not drawn
  }

  /** Another robot's page: forget and blank what the last one showed. */
  reset() {
    this.waiting = null;
    this.generation++;
    this.ctx.fillStyle = "#101418";
    this.ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    delete this.canvas.dataset.frames;
  }

  update(msg) {
    this.waiting = msg;
    if (!this.busy) this.next();
  }

  async next() {
    const msg = this.waiting;
    this.waiting = null;
    if (!msg) return;
    this.busy = true;
    const generation = this.generation;
    let bitmap = null;
    try {
      const fmt = String(msg.format).toLowerCase();
      const mime = fmt.includes("png") ? "image/png" : "image/jpeg";
      bitmap = await createImageBitmap(new Blob([msg.data], { type: mime }));
    } catch (err) {
      this.failed++;
      this.canvas.dataset.error = `image decode failed: ${err}`;
    }
    this.busy = false;
    // Not drawn when decoded for the robot whose page was left meanwhile.
    if (bitmap && generation === this.generation) {
      if (this.canvas.width !== bitmap.width || this.canvas.height !== bitmap.height) {
        this.canvas.width = bitmap.width;
        this.canvas.height = bitmap.height;
      }
      this.ctx.drawImage(bitmap, 0, 0);
      this.shown++;
      this.canvas.dataset.frames = String(this.shown);
    }
    bitmap?.close();
    if (this.waiting) this.next();
  }
}
