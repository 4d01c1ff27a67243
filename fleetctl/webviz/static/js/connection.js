// The page's one WebSocket to the fleet server (docs/design.md section 2).
//
// Signs in with a first text frame {"token": ...}, keeps the wanted subscriptions and
// re-sends them after every reconnect, reconnects with exponential backoff (reset by a
// welcome), and turns binary frames into decoded messages (reassembling fragments).
// Nothing here is unbounded: a frame whose type layout is still loading is dropped and
// counted, fragments are reassembled under a byte bound, and compressed frames (decompressed
// asynchronously, after reassembly) wait in a short per-topic queue that keeps each topic's
// messages in order.

import { COMPRESSED_TYPE, UnsupportedCompression, decompress } from "./compression.js";
import { Builder } from "./fb/builder.js";
import { readMetadata, Reader, DecodeError } from "./fb/reader.js";
import { FRAGMENT_TYPE, Reassembler } from "./fragments.js";
import { LinkHealth } from "./health.js";
import { probeThrottle, throttledClose } from "./loginthrottle.js";
import { Rules } from "./rules.js";

export const SUBSCRIPTION_TYPE = "amrl_msgs/msg/RobofleetSubscription";
const BACKOFF_MIN_MS = 250;
const BACKOFF_MAX_MS = 8000;
const MAX_LOG = 50; // server error frames kept for display
// Frames of one topic waiting behind an asynchronous decompression; more are dropped and
// counted (a 1 MB cloud inflates in a few ms, so a queue this long means the page is behind).
const MAX_INFLATE_QUEUE = 8;
// A socket that heard nothing for this long while the page waited for an answer (the
// welcome after it opened, or the robot list it asks for every 2 s) is given up and
// reconnected. A hung relay, or a dead path the TCP stack does not report (a server host
// that lost power, a laptop that changed networks), left the page saying "open" with the
// robot "online" for as long as the browser kept the socket: minutes.
export const SILENT_MS = 15000;
const WATCHDOG_MS = 1000;

/** Close codes that mean "do not retry with the same credentials". */
export const FATAL_CLOSE = { 4401: "the server refused the token", 4403: "this connection matches no identity in the auth map" };

export class Connection extends EventTarget {
  /**
   * @param {{url: string, failoverUrls?: string[], token: string|null,
   *          loader: import("./fb/layout.js").LayoutLoader,
   *          WebSocketImpl?: typeof WebSocket}} opts
   * failoverUrls: other relay replicas' WebSocket URLs; after a connection closes (or
   * fails to open) the next attempt goes to the next URL in [url, ...failoverUrls].
   * fetchImpl: the page's fetch, to ask whether a socket refused before it opened was the
   * relay's failed-login throttle (loginthrottle.js; tests replace it).
   */
  constructor({ url, failoverUrls = [], token, loader, WebSocketImpl = globalThis.WebSocket,
                fetchImpl = globalThis.fetch?.bind(globalThis) }) {
    super();
    this.urls = [url, ...failoverUrls.filter((u) => u !== url)];
    this.urlIndex = 0;
    this.url = url;
    this.token = token;
    this.loader = loader;
    this.WebSocketImpl = WebSocketImpl;
    this.fetchImpl = fetchImpl;
    this.ws = null;
    this.state = "idle"; // idle | connecting | open | disconnected | throttled | closed | refused
    // The relay refuses this address's tokens for now (too many failed logins): its hint
    // {retryAfterS}, kept until a socket opens; null: not throttled.
    this.throttle = null;
    this.opened = false; // the current socket opened
    this.lastErrorCode = null; // of the current socket's last error frame
    this.rules = new Rules();
    this.identities = [];
    this.wanted = new Set();
    this.active = new Set(); // regexes the server confirmed ("subscribed"), for display and tests
    this.backoffMs = BACKOFF_MIN_MS;
    this.retryTimer = null;
    this.stopped = false;
    this.health = new LinkHealth();
    this.reassembler = new Reassembler();
    this.stats = { framesIn: 0, decodeErrors: 0, droppedNoLayout: 0, sent: 0, decompressed: 0, droppedInflateQueue: 0, unsupported: 0 };
    this.inflating = new Map(); // topic -> {tail: Promise, queued: number}
    this.unsupported = new Map(); // topic -> message, for topics compressed with zstd
    this.errors = [];
    this.seq = 0n;
    this.waitingSinceMs = null; // the page waits for the server since (ms); null: not waiting
    this.watchdog = null;
  }

  start() {
    this.stopped = false;
    // Wrapper layouts are needed before the first fragment or compressed frame can even be
    // read: fetch them now, so a latched map sent once in fragments is not lost to a load.
    for (const t of [FRAGMENT_TYPE, COMPRESSED_TYPE]) this.loader.ensure(t).catch((err) => this.decodeFailed(err));
    this.open();
    clearInterval(this.watchdog);
    this.watchdog = setInterval(() => this.checkSilence(), WATCHDOG_MS);
  }

  stop() {
    this.stopped = true;
    clearInterval(this.watchdog);
    clearTimeout(this.retryTimer);
    this.ws?.close(1000, "page closed");
  }

  setStatus(state, detail = "", retryMs = this.backoffMs) {
    this.state = state;
    this.dispatchEvent(new CustomEvent("status", { detail: { state, detail, retryMs } }));
  }

  open() {
    this.setStatus("connecting");
    let ws;
    try {
      ws = new this.WebSocketImpl(this.url);
    } catch (err) {
      this.setStatus("refused", `bad server URL ${this.url}: ${err.message}`);
      return;
    }
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    this.opened = false;
    this.lastErrorCode = null;
    this.waitingSinceMs = Date.now(); // for the upgrade, then the welcome
    ws.onopen = () => {
      this.opened = true;
      this.throttle = null; // the upgrade went through: the address is within its budget
      if (this.token) ws.send(JSON.stringify({ token: this.token }));
    };
    ws.onmessage = (ev) => {
      this.waitingSinceMs = null; // any frame: the server is there
      return typeof ev.data === "string" ? this.onText(ev.data) : this.onBinary(ev.data);
    };
    ws.onclose = (ev) => this.onClose(ev);
  }

  /**
   * Give up a socket that has not answered for SILENT_MS (see there): the browser would
   * keep it, and the page would show stale data as live, until TCP gave up.
   */
  checkSilence(nowMs = Date.now()) {
    const ws = this.ws;
    if (!ws || this.stopped || this.waitingSinceMs === null || nowMs - this.waitingSinceMs <= SILENT_MS) return false;
    const silentS = Math.round((nowMs - this.waitingSinceMs) / 1000);
    ws.onopen = ws.onmessage = ws.onclose = null; // its close, whenever it comes, is not news
    try {
      ws.close(4000, "no answer");
    } catch {
      // closing a socket that never opened may throw in some browsers; it is dropped anyway
    }
    this.onClose({ code: null, reason: `no answer from the server for ${silentS} s`, silent: true });
    return true;
  }

  onClose(ev) {
    this.ws = null;
    this.waitingSinceMs = null;
    this.active.clear();
    if (this.stopped) return this.setStatus("closed");
    if (FATAL_CLOSE[ev.code]) return this.setStatus("refused", `${FATAL_CLOSE[ev.code]} (close ${ev.code})`);
    const throttle = throttledClose(ev, this.lastErrorCode);
    // Closed before it opened: the relay answers an upgrade from an address over its
    // failed-login budget with a 429 the page cannot see; ask it (loginthrottle.js).
    // A socket given up for silence was no 429 (that is answered at once).
    const asked = throttle || this.opened || ev.silent ? null : probeThrottle(this.url, this.fetchImpl);
    if (!asked) return this.retry(ev, throttle);
    asked.then((answer) => {
      if (!this.stopped && !this.ws) this.retry(ev, answer);
    });
  }

  /**
   * Schedule the next attempt after a close.
   * @param {{code: number, reason: string}} ev the close
   * @param {{retryAfterS: number|null}|false|null} throttle throttled (with the relay's
   *   hint), false: not, null: not known (a throttle seen before is kept)
   */
  retry(ev, throttle) {
    if (throttle) this.throttle = throttle;
    else if (throttle === false) this.throttle = null;
    let wait = this.backoffMs * (0.75 + Math.random() * 0.5); // jitter: robots and pages do not reconnect in lockstep
    const hintS = this.throttle?.retryAfterS;
    // Sooner would only be refused again; up to 20 % more spreads the pages and robots
    // behind one NAT. No usable hint: the backoff alone.
    if (hintS != null) wait = Math.max(wait, hintS * 1000 * (1 + Math.random() * 0.2));
    const why = ev.silent ? ev.reason : `close ${ev.code}${ev.reason ? `: ${ev.reason}` : ""}`;
    if (this.throttle) this.setStatus("throttled", why, wait);
    else this.setStatus("disconnected", why);
    // Replicas: the next attempt tries the next one (a dead replica refuses at once, so a
    // live one is reached within one backoff step); the backoff grows only after a full
    // round of the list.
    this.urlIndex = (this.urlIndex + 1) % this.urls.length;
    this.url = this.urls[this.urlIndex];
    if (this.urlIndex === 0) this.backoffMs = Math.min(BACKOFF_MAX_MS, this.backoffMs * 2);
    this.retryTimer = setTimeout(() => this.open(), wait);
  }

  onText(text) {
    let msg;
    try {
      msg = JSON.parse(text);
    } catch {
      return this.logError({ code: "bad_text", message: `unparseable text frame: ${text.slice(0, 80)}` });
    }
    switch (msg.type) {
      case "welcome":
        this.rules = new Rules(msg.rules ?? []);
        this.identities = msg.identities ?? [];
        this.backoffMs = BACKOFF_MIN_MS;
        this.setStatus("open");
        this.dispatchEvent(new CustomEvent("welcome", { detail: msg }));
        for (const re of this.wanted) this.sendSubscription(re, true);
        break;
      case "robots":
        this.dispatchEvent(new CustomEvent("robots", { detail: msg.robots ?? [] }));
        break;
      case "error":
        this.lastErrorCode = msg.code ?? null; // login_throttled comes before its 4429
        this.logError(msg);
        break;
      case "subscribed":
      case "unsubscribed":
        if (msg.type === "subscribed") this.active.add(msg.topic_regex);
        else this.active.delete(msg.topic_regex);
        this.dispatchEvent(new CustomEvent(msg.type, { detail: msg }));
        break;
      default:
        this.logError({ code: "unknown_text", message: `unknown text frame type ${msg.type}` });
    }
  }

  logError(err) {
    this.errors.push({ ...err, at: Date.now() });
    if (this.errors.length > MAX_LOG) this.errors.shift();
    this.dispatchEvent(new CustomEvent("server-error", { detail: err }));
  }

  onBinary(data) {
    this.stats.framesIn++;
    let bytes = new Uint8Array(data);
    let meta;
    try {
      meta = readMetadata(bytes);
      if (meta.type === FRAGMENT_TYPE) {
        const outer = meta;
        bytes = this.reassemble(meta, bytes);
        if (!bytes) return;
        meta = readMetadata(bytes);
        // The server checked permissions on the fragments' topic only: a message whose
        // own topic differs (or that nests another fragment) is refused, never delivered.
        if (meta.topic !== outer.topic || meta.type === FRAGMENT_TYPE) {
          throw new DecodeError(`reassembled message on ${meta.topic} came in fragments of ${outer.topic}`);
        }
      }
      // Health counts whole messages: a 20k-point cloud in 15 fragments is one message, not
      // 15 (lost fragments show up as the reassembler's drops and as seq gaps).
      this.health.record(meta, bytes.byteLength);
    } catch (err) {
      return this.decodeFailed(err);
    }
    // A latched message may be the only one the topic ever gets (a map sent once, replayed
    // by the server to this late subscriber): it waits for its layout instead of being
    // dropped, on the same ordered path as compressed frames.
    if (meta.type === COMPRESSED_TYPE || meta.latched || this.inflating.has(meta.topic)) return this.inOrder(meta, bytes);
    this.deliver(meta, bytes);
  }

  deliver(meta, bytes) {
    const layouts = this.loader.layouts;
    if (!layouts.has(meta.type)) {
      this.stats.droppedNoLayout++;
      this.loader.ensure(meta.type).catch((err) => this.decodeFailed(err));
      return;
    }
    try {
      const msg = new Reader(layouts).decode(bytes, meta.type);
      this.dispatchEvent(new CustomEvent("message", { detail: { meta, msg, size: bytes.byteLength } }));
    } catch (err) {
      this.decodeFailed(err);
    }
  }

  /**
   * Decompress (if compressed) and deliver after the topic's earlier frames: decompression
   * is asynchronous, and a plain frame must not overtake a compressed one before it.
   */
  inOrder(meta, bytes) {
    const topic = meta.topic;
    const entry = this.inflating.get(topic) ?? { tail: Promise.resolve(), queued: 0 };
    if (entry.queued >= MAX_INFLATE_QUEUE) {
      this.stats.droppedInflateQueue++;
      return;
    }
    entry.queued++;
    entry.tail = entry.tail
      .then(() => (meta.type === COMPRESSED_TYPE ? this.inflate(meta, bytes) : [meta, bytes]))
      .then(([m, b]) => this.deliverLoaded(m, b))
      .catch((err) => this.inflateFailed(topic, err))
      .finally(() => {
        if (--entry.queued === 0 && this.inflating.get(topic) === entry) this.inflating.delete(topic);
      });
    this.inflating.set(topic, entry);
  }

  async inflate(meta, bytes) {
    // Already asynchronous: wait for the layout instead of dropping the frame (a map may be
    // sent only once in a while).
    const layouts = await this.loader.ensure(COMPRESSED_TYPE);
    const msg = new Reader(layouts).decode(bytes, COMPRESSED_TYPE);
    const original = await decompress(meta.topic, msg, this.reassembler.maxBytes);
    this.stats.decompressed++;
    this.unsupported.delete(meta.topic);
    return [readMetadata(original), original];
  }

  async deliverLoaded(meta, bytes) {
    await this.loader.ensure(meta.type);
    this.deliver(meta, bytes);
  }

  inflateFailed(topic, err) {
    if (!(err instanceof UnsupportedCompression)) return this.decodeFailed(err);
    this.stats.unsupported++;
    if (this.unsupported.has(topic)) return; // said once per topic, not per frame
    this.unsupported.set(topic, err.message);
    this.logError({ code: "unsupported_compression", topic, message: err.message });
    this.dispatchEvent(new CustomEvent("unsupported", { detail: { topic, codec: err.codec, message: err.message } }));
  }

  reassemble(meta, bytes) {
    const layouts = this.loader.layouts;
    if (!layouts.has(FRAGMENT_TYPE)) {
      this.stats.droppedNoLayout++;
      this.loader.ensure(FRAGMENT_TYPE).catch((err) => this.decodeFailed(err));
      return null;
    }
    const frag = new Reader(layouts).decode(bytes, FRAGMENT_TYPE);
    return this.reassembler.feed(meta.topic, frag, performance.now() / 1000);
  }

  decodeFailed(err) {
    this.stats.decodeErrors++;
    const kind = err instanceof DecodeError ? "malformed_frame" : "layout";
    this.logError({ code: kind, message: String(err.message ?? err) });
  }

  /** Keep `re` subscribed across reconnects. */
  subscribe(re) {
    if (this.wanted.has(re)) return;
    this.wanted.add(re);
    if (this.state === "open") this.sendSubscription(re, true);
  }

  unsubscribe(re) {
    if (!this.wanted.delete(re)) return;
    if (this.state === "open") this.sendSubscription(re, false);
  }

  async sendSubscription(re, subscribe) {
    try {
      await this.sendMessage(SUBSCRIPTION_TYPE, "/subscriptions", { topic_regex: re, action: subscribe ? 1 : 0 });
    } catch (err) {
      this.logError({ code: "subscription", message: String(err.message ?? err) });
    }
  }

  listRobots() {
    if (this.state !== "open") return;
    this.ws.send(JSON.stringify({ type: "list_robots" }));
    this.waitingSinceMs ??= Date.now(); // answered by its robots frame (or any other)
  }

  /**
   * Encode and send one message of a ROS type.
   * @returns {Promise<number>} frame size (bytes)
   * @throws if not connected or the type's layout is unavailable
   */
  async sendMessage(typeName, topic, fields, { noDrop = false } = {}) {
    const layouts = await this.loader.ensure(typeName);
    if (this.state !== "open" || !this.ws) throw new Error("not connected to the fleet server");
    this.seq += 1n;
    const frame = new Builder(layouts).encode(typeName, {
      __metadata: { type: typeName, topic, no_drop: noDrop, publish_time_ns: BigInt(Date.now()) * 1000000n, seq: this.seq },
      ...fields,
    });
    this.ws.send(frame);
    this.stats.sent++;
    return frame.byteLength;
  }
}

/**
 * Where the relay at WebSocket URL *wsUrl* serves the type layouts: the same host and
 * port over HTTP(S), `/types/` (a replica's web listener serves the page and layouts).
 */
export function layoutsOf(wsUrl) {
  const url = new URL(wsUrl);
  url.protocol = url.protocol === "wss:" ? "https:" : "http:";
  url.pathname = "/types/";
  url.search = "";
  return url.href;
}
