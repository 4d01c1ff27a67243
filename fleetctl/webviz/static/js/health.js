// Per-topic link health: receive rate, latency from metadata.publish_time_ns and drops
// from gaps in metadata.seq (the sender's per-topic sequence number).
//
// Latency compares the robot's wall clock with the browser's, so it includes any clock
// offset between them; on one machine (tests, demo) it is exact.

const WINDOW_S = 5; // rate and latency are computed over the last WINDOW_S seconds
const MAX_SAMPLES = 512; // per topic; older samples are discarded (bounded memory)
const MAX_INTERVALS = 16; // arrival intervals kept per topic for its usual period
// A topic is overdue when nothing arrived for STALE_PERIODS of its usual period, and at
// least STALE_MIN_MS (a 10 Hz scan is overdue after 3 s, a 1 Hz status after 5 s).
export const STALE_PERIODS = 5;
export const STALE_MIN_MS = 3000;

export class TopicHealth {
  constructor() {
    this.samples = []; // [{t, latencyMs}]
    this.lastSeq = null;
    this.received = 0;
    this.gaps = 0; // messages the sender numbered but we never saw
    this.bytes = 0;
    this.lastLiveMs = null; // arrival of the last message that was not a kept (latched) one
    this.intervals = []; // ms between live arrivals, the last MAX_INTERVALS
  }

  /**
   * @param {{seq: bigint, publish_time_ns: bigint}} meta
   * @param {number} size frame size (bytes)
   * @param {number} nowMs browser wall clock (ms since epoch)
   */
  record(meta, size, nowMs) {
    this.firstMs ??= nowMs;
    this.received++;
    this.bytes += size;
    const seq = BigInt(meta.seq);
    // seq 0 means "the sender does not number this topic".
    if (!meta.latched) {
      if (this.lastSeq !== null && seq > this.lastSeq + 1n) this.gaps += Number(seq - this.lastSeq - 1n);
      if (seq !== 0n) this.lastSeq = seq;
    } else if (this.lastSeq !== null && seq > this.lastSeq) {
      // A latched message amid the live ones (a TF snapshot) continues the sequence. One the
      // server kept for this subscriber was numbered before the live ones that follow it
      // (or, after a reconnect, before those already seen): it starts no sequence, else
      // every message in between would count as a drop.
      this.lastSeq = seq;
    }
    if (!meta.latched) {
      if (this.lastLiveMs !== null) this.intervals.push(nowMs - this.lastLiveMs);
      if (this.intervals.length > MAX_INTERVALS) this.intervals.shift();
      this.lastLiveMs = nowMs;
    }
    const pub = Number(meta.publish_time_ns) / 1e6;
    // A latched message the server kept (a map sent minutes ago) is no latency sample.
    this.samples.push({ t: nowMs, latencyMs: pub > 0 && !meta.latched ? nowMs - pub : NaN });
    if (this.samples.length > MAX_SAMPLES) this.samples.splice(0, this.samples.length - MAX_SAMPLES);
  }

  /**
   * When this topic's data is old: nothing arrived for STALE_PERIODS of its usual period
   * (median arrival interval), at least STALE_MIN_MS. A topic with fewer than two live
   * messages (a latched map, a topic seen once) has no period and is never judged.
   * @returns {{lastMs: number, stale: boolean}|null} null: not judged
   */
  freshness(nowMs) {
    if (!this.intervals.length) return null;
    const sorted = [...this.intervals].sort((a, b) => a - b);
    const periodMs = sorted[sorted.length >> 1];
    return { lastMs: this.lastLiveMs, stale: nowMs - this.lastLiveMs > Math.max(STALE_MIN_MS, STALE_PERIODS * periodMs) };
  }

  /** @returns {{rateHz: number, latencyMs: number, drops: number, received: number}} */
  summary(nowMs) {
    const recent = this.samples.filter((s) => nowMs - s.t <= WINDOW_S * 1000);
    const lat = recent.map((s) => s.latencyMs).filter((x) => Number.isFinite(x)).sort((a, b) => a - b);
    // While the topic is younger than the window, its rate is over the time seen so far:
    // a 1 Hz status read 0.2, 0.4, 0.6 ... msg/s for the first five seconds of a page.
    let rateHz = recent.length / WINDOW_S;
    const first = this.samples[0];
    if (recent.length >= 2 && first === recent[0] && this.firstMs === first.t) {
      const spanMs = Math.max(nowMs - first.t, recent[recent.length - 1].t - first.t);
      if (spanMs > 0) rateHz = Math.min((recent.length - 1) / (spanMs / 1000), recent.length);
    }
    return {
      rateHz,
      latencyMs: lat.length ? lat[Math.floor(lat.length / 2)] : NaN,
      drops: this.gaps,
      received: this.received,
    };
  }
}

export class LinkHealth {
  constructor() {
    this.topics = new Map();
  }

  record(meta, size, nowMs = Date.now()) {
    let h = this.topics.get(meta.topic);
    if (!h) {
      h = new TopicHealth();
      this.topics.set(meta.topic, h);
    }
    h.record(meta, size, nowMs);
  }

  /**
   * Whether what a panel drew from *topics* is old: every judged topic (see
   * TopicHealth.freshness) is overdue; lastMs: the newest live arrival among them.
   * @returns {{stale: boolean, lastMs: number|null}} stale is false when none is judged
   */
  freshness(topics, nowMs = Date.now()) {
    const judged = topics.map((t) => this.topics.get(t)?.freshness(nowMs)).filter(Boolean);
    if (!judged.length) return { stale: false, lastMs: null };
    return { stale: judged.every((f) => f.stale), lastMs: Math.max(...judged.map((f) => f.lastMs)) };
  }

  /** Rows sorted by topic, optionally only those under a prefix. */
  rows(prefix = "", nowMs = Date.now()) {
    return [...this.topics.entries()]
      .filter(([t]) => t.startsWith(prefix))
      .sort(([a], [b]) => a.localeCompare(b))
      .map(([topic, h]) => ({ topic, ...h.summary(nowMs) }));
  }
}
