// Paces an expensive canvas so that drawing it takes at most a share of the page's main
// thread. The WebSocket's messages are handled on that same thread: a 3D scene redrawn at
// every TF update on a machine without GPU acceleration (Chromium's software WebGL, a VM,
// a remote desktop) took all of it, and every message then waited for the draws: the pose
// arrived 0.3-3 s late on the page while the link delivered it in 7 ms (docs/webviz.md,
// "The 3D scene's cost per message").
//
// A draw's cost cannot be timed around the draw call: WebGL queues commands, and the work
// (rasterizing, the compositor reading the canvas back) happens when the frame is
// committed. What the main thread loses shows in the animation frame's interval instead:
// the interval that follows a draw, less one display frame, is the draw's cost. The next
// draw then waits cost x (1 - share) / share, so the thread has the rest for messages. On a
// machine with a GPU the cost is about 0 and nothing waits.

export const DEFAULT_SHARE = 0.5;
const FRAME_MS = 1000 / 60;
const ALPHA = 0.3; // weight of the newest cost in the running estimate
const GAP_MS = 1000; // an interval longer than this is a hidden tab, not a draw's cost

export class DrawPacer {
  /** @param {number} share the part of the main thread the draws may take, (0, 1] */
  constructor(share = DEFAULT_SHARE) {
    if (!(share > 0 && share <= 1)) throw new RangeError(`share must be in (0, 1], got ${share}`);
    this.share = share;
    this.costMs = 0; // running estimate of one draw's cost to the main thread
    this.drewAt = null; // the animation frame of the last draw, until the next one is seen
    this.nextAt = -Infinity; // no draw before this time
    this.deferred = 0; // draws put off (counted, shown in the scene's stats)
  }

  /**
   * Called at every animation frame (timestamps in ms, one clock). Learns the last draw's
   * cost from this frame's interval. Returns whether a draw may happen now.
   */
  due(nowMs) {
    if (this.drewAt !== null) {
      const interval = nowMs - this.drewAt;
      if (interval <= GAP_MS) {
        const cost = Math.max(0, interval - FRAME_MS);
        this.costMs += ALPHA * (cost - this.costMs);
        this.nextAt = nowMs + (this.costMs * (1 - this.share)) / this.share;
      }
      this.drewAt = null;
    }
    return nowMs >= this.nextAt;
  }

  /** A draw that was wanted now and waits for its turn. */
  defer() {
    this.deferred++;
  }

  /** A draw happened in the animation frame of *nowMs*. */
  drew(nowMs) {
    this.drewAt = nowMs;
  }
}
