// Video panel: foxglove_msgs/msg/CompressedVideo decoded with WebCodecs' VideoDecoder.
//
// Per topic: the codec string comes from the bitstream (videocodec.js), is checked once
// with VideoDecoder.isConfigSupported (a missing codec is said in the panel, never
// guessed), and decoding starts at a keyframe. The gate (videogate.js) stops decoding at a
// seq gap, a decoder error or a decode queue that grows past MAX_DECODE_QUEUE, asks for a
// keyframe at most every 0.5 s, and resumes at the next keyframe, so no frame is ever drawn
// from a broken reference. Decoded frames are drawn at the next animation frame, latest
// wins (older ones are closed and counted as not shown).
//
// Behind (or after a gap) the decoder is kept, not closed or reset: what it holds is a
// whole chain and still decodes, and a keyframe references nothing, so it may follow any
// of it. Closing it threw that work away and paid the decoder's start again at every
// keyframe: on a busy page (the 3D scene rendered in software, 2 cores under load) that
// start alone outlasted the queue limit, and 556 submitted frames gave 9 decoded in 36 s.
// Kept, a page that cannot keep up decodes what it can (keyframes at the least).

import { inspectVideo } from "../videocodec.js";
import { VideoGate } from "../videogate.js";

const MAX_DECODE_QUEUE = 16; // chunks inside the decoder; more means the page is behind
const MAX_PENDING = 32; // chunks waiting for the one-time support check
const CODEC_HINT = "configure video codec h264, vp8, vp9 or av1 for this topic in the robot's client.yaml";

const supportCache = new Map(); // codec string -> Promise<boolean>

/** Whether this browser decodes `codec` (cached per codec string). */
function supported(codec) {
  if (!supportCache.has(codec)) {
    supportCache.set(codec, VideoDecoder.isConfigSupported({ codec, optimizeForLatency: true })
      .then((r) => !!r.supported)
      .catch(() => false));
  }
  return supportCache.get(codec);
}

/** Why this page cannot use WebCodecs at all, or null. */
export function webCodecsMissing() {
  if (typeof VideoDecoder !== "undefined") return null;
  if (globalThis.isSecureContext === false) {
    return "WebCodecs needs a secure context: open this page over https (the relay's web listener) or from localhost";
  }
  return "this browser has no WebCodecs VideoDecoder";
}

function timestampUs(msg, seq) {
  const t = msg.timestamp ?? {};
  const us = Number(t.sec ?? 0) * 1e6 + Math.floor(Number(t.nanosec ?? 0) / 1000);
  return us > 0 ? us : Number(seq) * 33333;
}

/** One video topic: its gate, its decoder and its counters. */
export class VideoStream {
  /**
   * @param {string} topic
   * @param {(topic: string) => void} requestKeyframe sends a KeyframeRequest
   */
  constructor(topic, requestKeyframe) {
    this.topic = topic;
    this.requestKeyframe = requestKeyframe;
    this.gate = new VideoGate();
    this.decoder = null;
    this.configured = null; // codec string the decoder is configured with
    this.pending = []; // [{chunk, codec, key}] while a support check runs
    this.checking = false;
    this.format = null;
    this.note = null; // what the panel says about this topic (missing codec, ...)
    this.latest = null; // VideoFrame waiting to be drawn
    this.size = null;
    this.shownAtMs = null; // Date.now() when the picture on the canvas was drawn
    this.counts = { decoded: 0, shown: 0, notShown: 0, droppedBehind: 0, errors: 0, unsupported: 0 };
  }

  /** Counters for the page and tests: gate's plus decoder's. */
  get stats() {
    const g = this.gate.stats;
    return { ...g, ...this.counts, skipped: g.skipped + this.counts.droppedBehind, state: this.gate.state, reason: this.gate.reason };
  }

  feed(meta, msg, nowMs = performance.now()) {
    const info = inspectVideo(msg.format, msg.data);
    const cannot = info.format ? webCodecsMissing() : `unknown video format "${msg.format}"; ${CODEC_HINT}`;
    if (cannot) {
      this.counts.unsupported++;
      return this.refuse(cannot);
    }
    if (this.format !== info.format) this.restart(info.format);
    const d = this.gate.frame(meta.seq, info.key, nowMs);
    if (d.request) this.requestKeyframe(this.topic);
    if (!d.decode) {
      if (this.gate.reason === "unsupported") this.counts.unsupported++;
      return;
    }
    const chunk = new EncodedVideoChunk({ type: info.key ? "key" : "delta", timestamp: timestampUs(msg, meta.seq), data: msg.data });
    this.pending.push({ chunk, codec: info.codec, key: info.key });
    if (this.pending.length > MAX_PENDING) return this.behind(nowMs);
    this.pump();
  }

  /** Stop for good (until the format changes), saying why; counted per frame. */
  refuse(note) {
    this.gate.broken("unsupported", 0);
    this.note = note;
  }

  restart(format) {
    this.format = format;
    this.gate = new VideoGate();
    this.pending = [];
    this.closeDecoder();
    this.note = null;
  }

  /** Feed pending chunks; a new codec string waits for its support check. */
  async pump() {
    while (this.pending.length && !this.checking) {
      const item = this.pending[0];
      // Only a keyframe can (re)configure: a delta frame has no SPS, so its codec string is
      // the default and says nothing about the stream.
      if (!this.decoder || (item.key && item.codec !== this.configured)) {
        this.checking = true;
        const ok = await supported(item.codec);
        this.checking = false;
        if (!ok) {
          this.counts.unsupported += this.pending.length;
          this.pending = [];
          this.closeDecoder();
          return this.refuse(`this browser cannot decode ${this.format} (VideoDecoder.isConfigSupported("${item.codec}") is false); ${CODEC_HINT}`);
        }
        if (this.pending[0] !== item) continue; // dropped meanwhile (behind)
        this.configure(item.codec);
      }
      this.pending.shift();
      try {
        this.decoder.decode(item.chunk);
      } catch (err) {
        this.failed(err);
        return;
      }
      if (this.decoder.decodeQueueSize > MAX_DECODE_QUEUE) this.behind(performance.now());
    }
  }

  configure(codec) {
    if (!this.decoder || this.decoder.state === "closed") {
      this.decoder = new VideoDecoder({ output: (f) => this.output(f), error: (e) => this.failed(e) });
    } else {
      this.decoder.reset(); // a new codec string at a keyframe: the old chain's output goes
    }
    this.decoder.configure({ codec, optimizeForLatency: true });
    this.configured = codec;
    this.note = null;
  }

  output(frame) {
    this.counts.decoded++;
    if (this.latest) {
      this.latest.close();
      this.counts.notShown++;
    }
    this.latest = frame;
  }

  failed(err) {
    this.counts.errors++;
    this.note = `decode error on ${this.topic}: ${err.message ?? err}; waiting for the next keyframe`;
    this.closeDecoder();
    this.pending = [];
    if (this.gate.broken("error", performance.now())) this.requestKeyframe(this.topic);
  }

  /** The page cannot keep up: drop what waits to be submitted and go on at the next
   * keyframe; the decoder keeps and finishes what it holds (see the top of this file). */
  behind(nowMs) {
    this.counts.droppedBehind += this.pending.length;
    this.pending = [];
    if (this.gate.broken("behind", nowMs)) this.requestKeyframe(this.topic);
  }

  closeDecoder() {
    if (this.decoder && this.decoder.state !== "closed") this.decoder.close();
    this.decoder = null;
    this.configured = null;
  }

  /** Draw the latest decoded frame on `canvas`; returns true if something was drawn. */
  draw(canvas, ctx) {
    const f = this.latest;
    if (!f) return false;
    this.latest = null;
    if (canvas.width !== f.displayWidth || canvas.height !== f.displayHeight) {
      canvas.width = f.displayWidth;
      canvas.height = f.displayHeight;
    }
    ctx.drawImage(f, 0, 0);
    this.size = [f.displayWidth, f.displayHeight];
    f.close();
    this.counts.shown++;
    this.shownAtMs = Date.now();
    return true;
  }

  close() {
    this.closeDecoder();
    this.latest?.close();
    this.latest = null;
  }
}

export class VideoView {
  /**
   * @param {{canvas: HTMLCanvasElement, status: HTMLElement, select: HTMLSelectElement}} els
   * @param {(topic: string) => void} requestKeyframe
   */
  constructor({ canvas, status, select }, requestKeyframe) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.statusEl = status;
    this.select = select;
    this.requestKeyframe = requestKeyframe;
    this.streams = new Map(); // topic -> VideoStream
    this.current = null;
    select.addEventListener("change", () => {
      this.current = select.value;
      this.renderStatus();
    });
  }

  /** Counters of every topic, for tests: {topic: stats}. */
  get stats() {
    return Object.fromEntries([...this.streams].map(([t, s]) => [t, s.stats]));
  }

  reset() {
    for (const s of this.streams.values()) s.close();
    this.streams.clear();
    this.current = null;
    this.select.replaceChildren();
    this.select.hidden = true; // no options: an empty selector stayed over the picture
    this.ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    this.renderStatus();
  }

  update(meta, msg) {
    let s = this.streams.get(meta.topic);
    if (!s) {
      s = new VideoStream(meta.topic, this.requestKeyframe);
      this.streams.set(meta.topic, s);
      this.select.append(new Option(meta.topic, meta.topic));
      this.select.hidden = this.streams.size < 2;
      this.current ??= meta.topic;
    }
    s.feed(meta, msg);
  }

  render() {
    const s = this.streams.get(this.current);
    for (const other of this.streams.values()) {
      if (other !== s && other.latest) {
        other.latest.close(); // decoded but not on screen: keep decoding, free the frame
        other.latest = null;
        other.counts.notShown++;
      }
    }
    if (s?.draw(this.canvas, this.ctx)) this.canvas.dataset.shown = String(s.counts.shown);
  }

  /**
   * How old the picture on the canvas is while its stream waits for a keyframe (frames
   * keep arriving, so the topic is not overdue, but the picture does not move).
   * @returns {number|null} ms; null: no picture, or the stream is decoding
   */
  frozenMs(nowMs = Date.now()) {
    const s = this.streams.get(this.current);
    if (!s || s.shownAtMs === null || s.gate.state !== "waiting" || s.gate.reason === "unsupported") return null;
    return nowMs - s.shownAtMs;
  }

  /** The status line: codec, counters, and whatever the panel must say (1 Hz). */
  renderStatus() {
    const s = this.streams.get(this.current);
    const el = this.statusEl;
    if (!s) {
      // Nothing came: the page's note over the picture says where video comes from
      // (app.js videoNote), so an operator knows what to change.
      el.textContent = webCodecsMissing() ?? "no video yet";
      el.classList.toggle("bad", !!webCodecsMissing());
      return;
    }
    const st = s.stats;
    // The state first: at the end of the three lines the box shows, "Waiting for a" was cut
    // off on a 300 px panel, and the picture looked live.
    const waiting = st.state === "waiting" && st.reason !== "unsupported"
      ? `Waiting for a keyframe (${st.reason === "start" ? "joined mid-stream" : st.reason}; ${st.requests} requested). ` : "";
    el.textContent = s.note
      ? `${s.topic}: ${s.note}`
      : `${waiting}${s.topic} ${s.format ?? ""} ${s.configured ?? ""}${s.size ? ` ${s.size[0]}x${s.size[1]}` : ""}: ` +
        `${st.decoded} decoded, ${st.shown} shown, ${st.skipped} skipped, ${st.gaps} gaps, ${st.errors} errors.`;
    el.classList.toggle("bad", !!s.note);
    Object.assign(this.canvas.dataset, { decoded: st.decoded, skipped: st.skipped, requests: st.requests });
  }
}
