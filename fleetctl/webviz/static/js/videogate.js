// When a video frame may be decoded, and when to ask the robot for a keyframe.
//
// Pure (no DOM): tests run it under node. A delta frame depends on the frames before it,
// so after a gap in the topic's metadata `seq` (the robot numbers each topic's messages), a
// decoder error, or frames the page had to drop, nothing is decoded until the next
// keyframe: a frame from a broken reference is never drawn. While waiting, the page asks
// for a keyframe (fleetctl_msgs/msg/KeyframeRequest on /keyframe_requests) at most once per
// `requestIntervalMs`.

export const REQUEST_INTERVAL_MS = 500;

export class VideoGate {
  /** @param {{requestIntervalMs?: number}} opts */
  constructor({ requestIntervalMs = REQUEST_INTERVAL_MS } = {}) {
    this.requestIntervalMs = requestIntervalMs;
    this.state = "waiting"; // waiting (for a keyframe) | decoding
    this.reason = "start"; // why waiting: start | gap | error | behind | unsupported
    this.lastSeq = null;
    this.lastRequestMs = -Infinity;
    this.stats = { received: 0, submitted: 0, skipped: 0, gaps: 0, broken: 0, requests: 0 };
  }

  /**
   * Decide about one received frame.
   * @param {bigint} seq the frame's metadata seq (0n: the sender does not number frames)
   * @param {boolean} key the frame is a keyframe
   * @param {number} nowMs a clock in ms (for the request rate)
   * @returns {{decode: boolean, resume: boolean, request: boolean}} `resume`: decoding
   *     restarts at this keyframe (a keyframe needs no decoder reset: views/video.js
   *     keeps its decoder); `request`: send a KeyframeRequest now
   */
  frame(seq, key, nowMs) {
    this.stats.received++;
    seq = BigInt(seq);
    if (seq !== 0n) {
      // A frame older than the last one (a replay) breaks the chain as much as a lost one.
      if (this.lastSeq !== null && seq !== this.lastSeq + 1n) {
        this.stats.gaps++;
        if (this.state === "decoding") this.stop("gap");
      }
      this.lastSeq = seq;
    }
    let resume = false;
    if (this.state === "waiting" && key && this.reason !== "unsupported") {
      this.state = "decoding";
      resume = true;
    }
    if (this.state === "decoding") {
      this.stats.submitted++;
      return { decode: true, resume, request: false };
    }
    this.stats.skipped++;
    return { decode: false, resume: false, request: this.reason !== "unsupported" && this.mayRequest(nowMs) };
  }

  /**
   * Stop decoding until the next keyframe.
   * @param {"gap"|"error"|"behind"|"unsupported"} reason ("unsupported": for good)
   * @param {number} nowMs
   * @returns {boolean} send a KeyframeRequest now
   */
  broken(reason, nowMs) {
    this.stop(reason);
    return reason !== "unsupported" && this.mayRequest(nowMs);
  }

  stop(reason) {
    if (this.state === "decoding") this.stats.broken++;
    this.state = "waiting";
    this.reason = reason;
  }

  mayRequest(nowMs) {
    if (nowMs - this.lastRequestMs < this.requestIntervalMs) return false;
    this.lastRequestMs = nowMs;
    this.stats.requests++;
    return true;
  }
}
