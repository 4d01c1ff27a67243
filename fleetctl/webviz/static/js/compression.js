// fleetctl_msgs/msg/Compressed frames (docs/design.md section 1, docs/wire.md): the
// compressed bytes of a whole frame, decompressed after fragment reassembly and before
// decoding. Codec 2 (raw deflate, RFC 1951) is decoded natively by the browser with
// DecompressionStream('deflate-raw'); codec 1 (zstd) is what fleetctl clients prefer, but no
// browser decodes it (Chromium: gzip, deflate, deflate-raw only), so it is reported, not
// decoded, and the robot's config must say `compression: deflate` for topics shown here.
//
// Bounded like the Python side: nothing past original_bytes is kept, and the input goes in
// small slices so a bomb (a few KB inflating to gigabytes) is stopped after one slice's worth.

import { DecodeError, readMetadata } from "./fb/reader.js";
import { FRAGMENT_TYPE } from "./fragments.js";

export const COMPRESSED_TYPE = "fleetctl_msgs/msg/Compressed";
export const CODEC = { ZSTD: 1, DEFLATE: 2 };
const CODEC_NAMES = { [CODEC.ZSTD]: "zstd", [CODEC.DEFLATE]: "deflate" };
// Input slice fed to the decompressor at a time: deflate expands at most ~1032:1, so one
// slice yields at most ~17 MB before the output check runs, even in an implementation that
// ignores backpressure inside a chunk (Node 20's does not; slicing costs nothing measurable:
// 1 MiB from 0.7 MB of deflate in 12-23 ms sliced, 12-20 ms in one write, Node 20).
const SLICE_BYTES = 16 * 1024;

/** A frame compressed with a codec this page cannot decode (zstd). */
export class UnsupportedCompression extends Error {
  constructor(topic, codec) {
    const name = CODEC_NAMES[codec] ?? `codec ${codec}`;
    super(`${topic} is compressed with ${name}, which browsers cannot decode; ` +
      "set compression: deflate for this topic in the robot's client.yaml");
    this.name = "UnsupportedCompression";
    this.topic = topic;
    this.codec = name;
  }
}

/**
 * The original frame of a decoded Compressed message.
 * @param {string} topic the Compressed frame's metadata topic
 * @param {{codec: number, original_bytes: number, payload: Uint8Array}} msg
 * @param {number} maxBytes largest original frame accepted (bytes)
 * @returns {Promise<Uint8Array>} the original frame, checked to be on the same topic
 * @throws {UnsupportedCompression} for zstd; {DecodeError} for everything malformed
 */
export async function decompress(topic, msg, maxBytes) {
  const original = Number(msg.original_bytes);
  if (msg.codec === CODEC.ZSTD) throw new UnsupportedCompression(topic, msg.codec);
  if (msg.codec !== CODEC.DEFLATE) throw new DecodeError(`${topic}: unknown compression codec ${msg.codec}`);
  if (original > maxBytes) throw new DecodeError(`${topic}: compressed frame declares ${original} bytes, over ${maxBytes}`);
  const out = await inflateRaw(msg.payload, original, topic);
  const meta = readMetadata(out);
  // The server checked the sender's right to the outer topic only.
  if (meta.topic !== topic) throw new DecodeError(`${topic}: compressed frame holds a frame on ${meta.topic}`);
  if (meta.type === COMPRESSED_TYPE || meta.type === FRAGMENT_TYPE) {
    throw new DecodeError(`${topic}: compressed frame holds a ${meta.type} frame`);
  }
  return out;
}

/**
 * Inflate raw deflate data to exactly `original` bytes.
 * @returns {Promise<Uint8Array>}
 * @throws {DecodeError} corrupt, truncated or trailing data, or another size than declared
 */
export async function inflateRaw(payload, original, what = "deflate data") {
  const stream = new DecompressionStream("deflate-raw");
  const writer = stream.writable.getWriter();
  const reader = stream.readable.getReader();
  // Writes wait for reads (the readable side has no buffer), so at most one slice's output
  // exists beyond what is checked below.
  const feeding = (async () => {
    for (let at = 0; at < payload.length; at += SLICE_BYTES) {
      await writer.write(payload.subarray(at, at + SLICE_BYTES));
    }
    await writer.close();
  })().catch(() => {}); // a failure surfaces on the reader
  const out = new Uint8Array(original);
  let got = 0;
  try {
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      if (got + value.length > original) throw new DecodeError(`${what}: inflates past the declared ${original} bytes`);
      out.set(value, got);
      got += value.length;
    }
  } catch (err) {
    reader.cancel().catch(() => {});
    if (err instanceof DecodeError) throw err;
    throw new DecodeError(`${what}: corrupt deflate data (${err.message ?? err})`);
  } finally {
    await feeding;
  }
  if (got !== original) throw new DecodeError(`${what}: inflates to ${got} bytes, not the declared ${original}`);
  return out;
}
