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
    try {
      const fmt = String(msg.format).toLowerCase();
      const mime = fmt.includes("png") ? "image/png" : "image/jpeg";
      const bitmap = await createImageBitmap(new Blob([msg.data], { type: mime }));
      if (this.canvas.width !== bitmap.width || this.canvas.height !== bitmap.height) {
        this.canvas.width = bitmap.width;
        this.canvas.height = bitmap.height;
      }
      this.ctx.drawImage(bitmap, 0, 0);
      bitmap.close();
      this.shown++;
      this.canvas.dataset.frames = String(this.shown);
    } catch (err) {
      this.failed++;
      this.canvas.dataset.error = `image decode failed: ${err}`;
    } finally {
      this.busy = false;
    }
    if (this.waiting) this.next();
  }
}
