import { test } from "node:test";
import assert from "node:assert/strict";
import { Reassembler, FRAGMENT_TYPE } from "../../../fleetctl/webviz/static/js/fragments.js";
import { Reader, readMetadata } from "../../../fleetctl/webviz/static/js/fb/reader.js";
import { HAVE, cases, frame, layoutsFor } from "./cases.mjs";

const skip = HAVE ? false : "FLEETCTL_WEBVIZ_CASES not set (run through pytest)";

const frag = (id, index, count, bytes, total) => ({ message_id: BigInt(id), index, count, total_bytes: total, payload: Uint8Array.from(bytes) });

test("reassembles Python-split fragments, in any order, to the original frame", { skip }, () => {
  const layouts = layoutsFor(FRAGMENT_TYPE);
  const reader = new Reader(layouts);
  const n = cases.fragments.count;
  const original = frame(cases.fragments.original);
  const order = [...Array(n).keys()].reverse();
  const r = new Reassembler();
  let out = null;
  for (const i of order) {
    const bytes = frame(`frag${i}.bin`);
    const meta = readMetadata(bytes);
    assert.equal(meta.type, FRAGMENT_TYPE);
    assert.equal(meta.topic, "/r1/points");
    const got = r.feed(meta.topic, reader.decode(bytes, FRAGMENT_TYPE), 0);
    if (i !== order[order.length - 1]) assert.equal(got, null);
    else out = got;
  }
  assert.deepEqual(out, original);
  assert.equal(r.buffered, 0);
});

test("a newer message_id drops the incomplete one and counts it", () => {
  const r = new Reassembler();
  assert.equal(r.feed("/t", frag(1, 0, 2, [1, 2], 4), 0), null);
  assert.equal(r.feed("/t", frag(2, 0, 2, [5, 6], 4), 0), null);
  assert.equal(r.dropped.superseded, 1);
  assert.deepEqual(r.feed("/t", frag(2, 1, 2, [7, 8], 4), 0), Uint8Array.from([5, 6, 7, 8]));
  assert.equal(r.feed("/t", frag(1, 1, 2, [3, 4], 4), 0), null); // late part of the dropped one
  assert.equal(r.dropped.superseded, 2);
  assert.equal(r.buffered, 0);
});

test("timeout, byte bound and malformed fragments are dropped and counted", () => {
  const r = new Reassembler(6, 1.0);
  r.feed("/a", frag(1, 0, 2, [1, 2, 3], 6), 0);
  assert.equal(r.feed("/b", frag(1, 0, 2, [1], 2), 5), null); // /a expires at t=5
  assert.equal(r.dropped.timeout, 1);
  r.feed("/c", frag(1, 0, 3, [1, 2, 3, 4, 5], 15), 5);
  assert.equal(r.feed("/c", frag(1, 1, 3, [1, 2, 3, 4, 5], 15), 5), null);
  assert.equal(r.dropped.overflow, 1);
  assert.equal(r.feed("/d", frag(1, 3, 2, [1], 2), 5), null);
  assert.equal(r.dropped.malformed, 1);
  assert.ok(r.buffered <= 6);
});
