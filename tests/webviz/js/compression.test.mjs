import { test } from "node:test";
import assert from "node:assert/strict";
import { deflateRawSync } from "node:zlib";
import {
  COMPRESSED_TYPE, UnsupportedCompression, decompress, inflateRaw,
} from "../../../fleetctl/webviz/static/js/compression.js";
import { Connection } from "../../../fleetctl/webviz/static/js/connection.js";
import { DecodeError, Reader, readMetadata } from "../../../fleetctl/webviz/static/js/fb/reader.js";
import { FRAGMENT_TYPE } from "../../../fleetctl/webviz/static/js/fragments.js";
import { HAVE, cases, frame, layoutsFor } from "./cases.mjs";

const skip = HAVE ? false : "FLEETCTL_WEBVIZ_CASES not set (run through pytest)";
const GRID = "nav_msgs/msg/OccupancyGrid";
const MiB = 1 << 20;

function compressedMsg(bytes) {
  return new Reader(layoutsFor(COMPRESSED_TYPE)).decode(bytes, COMPRESSED_TYPE);
}

test("a Python deflate-compressed map inflates to the original frame and decodes", { skip }, async () => {
  const packed = frame("map_deflate.bin");
  const meta = readMetadata(packed);
  assert.equal(meta.type, COMPRESSED_TYPE);
  assert.equal(meta.seq, 9n); // the original's metadata, copied
  const original = await decompress(meta.topic, compressedMsg(packed), 64 * MiB);
  assert.deepEqual(original, frame("map_original.bin"));
  const grid = new Reader(layoutsFor(GRID)).decode(original, GRID);
  assert.equal(grid.info.width, cases.compressed.width);
  const counts = {};
  for (const v of grid.data) counts[v] = (counts[v] ?? 0) + 1;
  assert.deepEqual(counts, cases.compressed.cells);
});

test("zstd is reported with what to change, not decoded", { skip }, async () => {
  const packed = frame("map_zstd.bin");
  await assert.rejects(decompress("/r2/map", compressedMsg(packed), 64 * MiB), (err) => {
    assert.ok(err instanceof UnsupportedCompression);
    assert.match(err.message, /compressed with zstd, which browsers cannot decode; set compression: deflate/);
    return true;
  });
});

test("bad declared sizes, codecs and topics are DecodeErrors", { skip }, async () => {
  const msg = compressedMsg(frame("map_deflate.bin"));
  const bad = [
    { ...msg, original_bytes: msg.original_bytes - 1 },
    { ...msg, original_bytes: msg.original_bytes + 1 },
    { ...msg, codec: 7 },
    { ...msg, payload: msg.payload.map((b) => b ^ 0x5a) },
    { ...msg, payload: msg.payload.subarray(0, msg.payload.length >> 1) },
  ];
  for (const m of bad) await assert.rejects(decompress("/r1/map", m, 64 * MiB), DecodeError);
  await assert.rejects(decompress("/r1/map", msg, msg.original_bytes - 1), /over/);
  await assert.rejects(decompress("/r9/map", msg, 64 * MiB), /holds a frame on \/r1\/map/);
});

test("a deflate bomb stops at the declared size", async () => {
  const bomb = new Uint8Array(deflateRawSync(Buffer.alloc(64 * MiB))); // ~64 KB
  const before = process.memoryUsage().arrayBuffers;
  await assert.rejects(inflateRaw(bomb, 1000), /inflates past the declared 1000 bytes/);
  assert.ok(process.memoryUsage().arrayBuffers - before < 32 * MiB);
  await assert.rejects(inflateRaw(new Uint8Array([1, 2, 3]), 10), DecodeError);
  const ok = deflateRawSync(Buffer.from("hello"));
  await assert.rejects(inflateRaw(new Uint8Array(ok).subarray(0, 3), 5), DecodeError); // truncated
  assert.deepEqual(await inflateRaw(new Uint8Array(ok), 5), new TextEncoder().encode("hello"));
  // (Trailing junk after the deflate end: Chromium's DecompressionStream rejects it, as the
  // Compression Streams spec says; Node 20's ignores it, so it is not asserted here.)
});

/** A Connection fed frames directly (no WebSocket); layouts come from the fixtures. */
function connection() {
  const layouts = layoutsFor(COMPRESSED_TYPE, FRAGMENT_TYPE, GRID);
  const loader = { layouts, ensure: async () => layouts };
  const conn = new Connection({ url: "ws://unused/", token: null, loader });
  const got = [];
  conn.addEventListener("message", (e) => got.push(e.detail));
  const said = [];
  conn.addEventListener("unsupported", (e) => said.push(e.detail));
  return { conn, got, said };
}

async function until(predicate, what) {
  const deadline = Date.now() + 5000;
  while (!predicate()) {
    if (Date.now() > deadline) throw new Error(`timed out waiting for ${what}`);
    await new Promise((resolve) => setImmediate(resolve));
  }
}

test("Connection: fragments -> reassembly -> inflate -> decode, in order with plain frames", { skip }, async () => {
  const { conn, got } = connection();
  for (let j = 0; j < cases.compressed.fragments; j++) conn.onBinary(frame(`map_frag${j}.bin`).buffer);
  conn.onBinary(frame("map_plain_after.bin").buffer); // must wait behind the inflation
  await until(() => got.length === 2, "two maps");
  assert.deepEqual(got.map((m) => m.meta.seq), [9n, 10n]);
  assert.equal(got[0].meta.type, GRID);
  assert.equal(got[0].msg.info.width, cases.compressed.width);
  assert.equal(conn.stats.decompressed, 1);
  assert.equal(conn.stats.decodeErrors, 0);
  await until(() => conn.inflating.size === 0, "the queue to drain");
});

test("Connection: a zstd topic is said once per topic, and nothing is delivered", { skip }, async () => {
  const { conn, got, said } = connection();
  conn.onBinary(frame("map_zstd.bin").buffer);
  conn.onBinary(frame("map_zstd.bin").buffer);
  await until(() => conn.stats.unsupported === 2, "both frames");
  assert.equal(got.length, 0);
  assert.equal(said.length, 1);
  assert.equal(said[0].topic, "/r2/map");
  assert.match(conn.unsupported.get("/r2/map"), /set compression: deflate for this topic/);
  assert.equal(conn.errors[0].code, "unsupported_compression");
});

test("Connection: a message whose own topic differs from its fragments' is refused", { skip }, async () => {
  const layouts = layoutsFor(FRAGMENT_TYPE);
  const loader = { layouts, ensure: async () => layouts };
  const conn = new Connection({ url: "ws://unused/", token: null, loader });
  const got = [];
  conn.addEventListener("message", (e) => got.push(e.detail));
  for (let j = 0; j < cases.fragments.smuggled; j++) conn.onBinary(frame(`smuggled${j}.bin`).buffer);
  assert.equal(got.length, 0);
  assert.equal(conn.stats.decodeErrors, 1);
  assert.match(conn.errors[0].message, /came in fragments of \/r9\/allowed/);
});
