// Reassembly of fleetctl_msgs/msg/Fragment frames (docs/design.md section 1).
//
// Bounded: at most one message in flight per topic, and maxBytes over all topics. An
// incomplete message is dropped (and counted) when a newer message_id of its topic starts,
// when it is older than timeoutS, or when accepting a fragment would pass maxBytes.

const MAX_TOPICS = 4096;

export const FRAGMENT_TYPE = "fleetctl_msgs/msg/Fragment";

export class Reassembler {
  /**
   * @param {number} maxBytes bound on buffered payload bytes over all topics (bytes)
   * @param {number} timeoutS an incomplete message older than this is dropped (s)
   */
  constructor(maxBytes = 64 * 1024 * 1024, timeoutS = 10) {
    this.maxBytes = maxBytes;
    this.timeoutS = timeoutS;
    this.partial = new Map(); // topic -> {id, count, total, parts, got, bytes, startS}
    this.newest = new Map(); // topic -> newest message_id seen (late fragments of older ones are dropped)
    this.buffered = 0;
    this.dropped = { superseded: 0, timeout: 0, overflow: 0, malformed: 0 };
  }

  /**
   * Feed one decoded fragment.
   * @param {string} topic the fragment's metadata topic
   * @param {{message_id: bigint, index: number, count: number, total_bytes: number, payload: Uint8Array}} frag
   * @param {number} nowS current time (s, any monotonic origin)
   * @returns {Uint8Array|null} the original frame once complete, else null
   */
  feed(topic, frag, nowS) {
    this.expire(nowS);
    const { index, count, total_bytes: total, payload } = frag;
    const id = BigInt(frag.message_id);
    if (!(count > 0) || !(index >= 0 && index < count) || payload.length > total) {
      this.dropped.malformed++;
      return null;
    }
    const newest = this.newest.get(topic);
    if (newest !== undefined && id < newest) {
      this.dropped.superseded++; // a late fragment of a message already completed or given up
      return null;
    }
    this.remember(topic, id);
    let cur = this.partial.get(topic);
    if (cur && cur.id !== id) {
      this.discard(topic, "superseded");
      cur = undefined;
    }
    if (!cur) {
      cur = { id, count, total, parts: new Array(count), got: 0, bytes: 0, startS: nowS };
      this.partial.set(topic, cur);
    }
    if (cur.count !== count || cur.total !== total) {
      this.discard(topic, "malformed");
      return null;
    }
    if (cur.parts[index] !== undefined) return null; // duplicate: ignore
    if (this.buffered + payload.length > this.maxBytes || cur.bytes + payload.length > total) {
      this.discard(topic, "overflow");
      return null;
    }
    // Copy: the payload is a view on a frame that the caller may reuse.
    cur.parts[index] = payload.slice();
    cur.got++;
    cur.bytes += payload.length;
    this.buffered += payload.length;
    return cur.got === cur.count ? this.complete(topic, cur) : null;
  }

  remember(topic, id) {
    this.newest.delete(topic);
    this.newest.set(topic, id);
    // Bounded: forget the least recently active topics beyond MAX_TOPICS.
    if (this.newest.size > MAX_TOPICS) this.newest.delete(this.newest.keys().next().value);
  }

  complete(topic, cur) {
    this.partial.delete(topic);
    this.buffered -= cur.bytes;
    if (cur.bytes !== cur.total) {
      this.dropped.malformed++;
      return null;
    }
    const out = new Uint8Array(cur.total);
    let at = 0;
    for (const p of cur.parts) {
      out.set(p, at);
      at += p.length;
    }
    return out;
  }

  discard(topic, reason) {
    const cur = this.partial.get(topic);
    if (!cur) return;
    this.partial.delete(topic);
    this.buffered -= cur.bytes;
    this.dropped[reason]++;
  }

  expire(nowS) {
    for (const [topic, cur] of this.partial) {
      if (nowS - cur.startS > this.timeoutS) this.discard(topic, "timeout");
    }
  }

  totalDropped() {
    return Object.values(this.dropped).reduce((a, b) => a + b, 0);
  }
}
