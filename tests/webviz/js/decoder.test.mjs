import { test } from "node:test";
import assert from "node:assert/strict";
import { Reader, readMetadata, DecodeError } from "../../../fleetctl/webviz/static/js/fb/reader.js";
import { LayoutError } from "../../../fleetctl/webviz/static/js/fb/layout.js";
import { HAVE, cases, frame, layoutsFor, mismatch } from "./cases.mjs";

const skip = HAVE ? false : "FLEETCTL_WEBVIZ_CASES not set (run through pytest)";

test("decodes every Python-encoded frame to the same values", { skip }, () => {
  assert.ok(cases.decode.length >= 10);
  for (const c of cases.decode) {
    const bytes = frame(c.name);
    const meta = readMetadata(bytes);
    assert.equal(meta.type, c.type, c.name);
    const msg = new Reader(layoutsFor(c.type)).decode(bytes, c.type);
    assert.equal(msg.__metadata.topic, meta.topic);
    assert.equal(mismatch(msg, c.expected), null, `${c.name} (${c.type})`);
  }
});

test("metadata: seq and publish_time_ns are exact 64-bit values", { skip }, () => {
  const c = cases.decode.find((x) => !x.golden);
  const meta = readMetadata(frame(c.name));
  assert.equal(typeof meta.publish_time_ns, "bigint");
  assert.equal(meta.publish_time_ns, 1700000000123456789n);
  assert.equal(meta.seq, 1n);
});

test("large numeric vectors are zero-copy views on the frame", { skip }, () => {
  const c = cases.decode.find((x) => x.type === "sensor_msgs/msg/LaserScan");
  const bytes = frame(c.name);
  const msg = new Reader(layoutsFor(c.type)).decode(bytes, c.type);
  assert.ok(msg.ranges instanceof Float32Array);
  assert.equal(msg.ranges.buffer, bytes.buffer, "ranges should view the frame's buffer");
  const cloud = cases.decode.find((x) => x.type === "sensor_msgs/msg/PointCloud2");
  const cb = frame(cloud.name);
  const cm = new Reader(layoutsFor(cloud.type)).decode(cb, cloud.type);
  assert.ok(cm.data instanceof Uint8Array);
  assert.equal(cm.data.buffer, cb.buffer);
});

test("an unaligned frame still decodes (typed arrays are copied then)", { skip }, () => {
  const c = cases.decode.find((x) => x.type === "sensor_msgs/msg/LaserScan");
  const src = frame(c.name);
  const shifted = new Uint8Array(src.length + 1);
  shifted.set(src, 1);
  const msg = new Reader(layoutsFor(c.type)).decode(shifted.subarray(1), c.type);
  assert.equal(mismatch(msg, c.expected), null);
});

test("every truncation of a frame throws DecodeError, never anything else", { skip }, () => {
  for (const c of cases.decode.filter((x) => !x.golden).slice(0, 8)) {
    const bytes = frame(c.name);
    const reader = new Reader(layoutsFor(c.type));
    for (let n = 0; n < bytes.length; n += Math.max(1, bytes.length >> 6)) {
      const cut = bytes.slice(0, n);
      try {
        reader.decode(cut, c.type);
      } catch (err) {
        assert.ok(err instanceof DecodeError, `${c.type} cut at ${n}: ${err}`);
      }
    }
  }
});

test("random corruption throws DecodeError or decodes; never a crash", { skip }, () => {
  let seed = 12345;
  const rand = () => ((seed = (seed * 1103515245 + 12345) >>> 0) / 2 ** 32);
  for (const c of cases.decode.filter((x) => !x.golden)) {
    const reader = new Reader(layoutsFor(c.type));
    for (let trial = 0; trial < 40; trial++) {
      const bytes = frame(c.name);
      for (let k = 0; k < 4; k++) bytes[Math.floor(rand() * bytes.length)] = Math.floor(rand() * 256);
      try {
        reader.decode(bytes, c.type);
      } catch (err) {
        assert.ok(err instanceof DecodeError, `${c.type}: ${err.name}: ${err.message}`);
      }
    }
  }
});

test("a type without a layout is a LayoutError", { skip }, () => {
  const c = cases.decode[0];
  assert.throws(() => new Reader(layoutsFor(c.type)).decode(frame(c.name), "nope_msgs/msg/Nope"), LayoutError);
});

test("an empty or tiny frame is a DecodeError", () => {
  assert.throws(() => readMetadata(new Uint8Array(0)), DecodeError);
  assert.throws(() => readMetadata(new Uint8Array([4, 0, 0, 0])), DecodeError);
  assert.throws(() => readMetadata(new Uint8Array([255, 255, 255, 127, 0, 0, 0, 0])), DecodeError);
});
