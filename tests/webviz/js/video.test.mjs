import { test } from "node:test";
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { join } from "node:path";
import { DEFAULT_CODECS, annexBUnits, inspectVideo, normalizeFormat } from "../../../fleetctl/webviz/static/js/videocodec.js";
import { VideoGate } from "../../../fleetctl/webviz/static/js/videogate.js";
import { DIR, HAVE, cases } from "./cases.mjs";

const skip = HAVE ? false : "FLEETCTL_WEBVIZ_CASES not set (run through pytest)";

test("keyframes of real PyAV streams (x264, x265, libvpx, libvpx-vp9, SVT-AV1) are found", { skip }, () => {
  const seen = {};
  for (const u of cases.video) {
    const data = new Uint8Array(readFileSync(join(DIR, "video", u.name)));
    const info = inspectVideo(u.format, data);
    assert.equal(info.format, u.format);
    assert.equal(info.key, u.key, `${u.name}: keyframe flag`);
    if (u.codec) assert.equal(info.codec, u.codec, `${u.name}: codec string from the SPS`);
    seen[u.format] = (seen[u.format] ?? 0) + (u.key ? 1 : 0);
  }
  assert.deepEqual(Object.keys(seen).sort(), ["av1", "h264", "h265", "vp8", "vp9"]);
  for (const [f, keys] of Object.entries(seen)) assert.ok(keys >= 2, `${f}: ${keys} keyframes`);
});

test("codec strings: vp9 and av1 from their headers, defaults otherwise", { skip }, () => {
  const first = (f) => new Uint8Array(readFileSync(join(DIR, "video", `${f}_0.bin`)));
  assert.equal(inspectVideo("vp9", first("vp9")).codec, "vp09.00.10.08");
  assert.equal(inspectVideo("av1", first("av1")).codec, "av01.0.04M.08");
  assert.equal(inspectVideo("vp8", first("vp8")).codec, "vp8");
  assert.equal(inspectVideo("h265", first("h265")).codec, DEFAULT_CODECS.h265);
});

test("formats are normalized; unknown formats and junk are not keyframes", () => {
  assert.equal(normalizeFormat("H.264"), "h264");
  assert.equal(normalizeFormat("HEVC"), "h265");
  assert.equal(normalizeFormat("mjpeg"), null);
  assert.deepEqual(inspectVideo("mjpeg", new Uint8Array(4)), { format: null, key: false, codec: null });
  for (const f of ["h264", "h265", "vp8", "vp9", "av1"]) {
    for (const junk of [new Uint8Array(0), new Uint8Array([0, 0, 1]), new Uint8Array([0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff])]) {
      const info = inspectVideo(f, junk);
      assert.equal(info.key, false, `${f} ${junk}`);
      assert.equal(info.codec, DEFAULT_CODECS[f]);
    }
  }
  // A delta h264 unit keeps the default codec (no SPS in it).
  assert.equal(inspectVideo("h264", new Uint8Array([0, 0, 0, 1, 0x41, 0x9a])).codec, DEFAULT_CODECS.h264);
  assert.deepEqual(annexBUnits(new Uint8Array([0, 0, 0, 1, 0x67, 1, 0, 0, 1, 0x68])), [{ start: 4, end: 6 }, { start: 9, end: 10 }]);
});

test("the gate waits for a keyframe, decodes on, and stops at a seq gap until the next one", () => {
  const g = new VideoGate({ requestIntervalMs: 500 });
  // Joined mid-stream: delta frames are skipped and a keyframe is requested once per 0.5 s.
  assert.deepEqual(g.frame(5n, false, 0), { decode: false, resume: false, request: true });
  assert.deepEqual(g.frame(6n, false, 100), { decode: false, resume: false, request: false });
  assert.deepEqual(g.frame(7n, true, 200), { decode: true, resume: true, request: false });
  assert.deepEqual(g.frame(8n, false, 233), { decode: true, resume: false, request: false });
  // Frame 9 lost: 10 depends on it.
  assert.deepEqual(g.frame(10n, false, 600), { decode: false, resume: false, request: true });
  assert.equal(g.reason, "gap");
  assert.deepEqual(g.frame(11n, false, 700), { decode: false, resume: false, request: false });
  assert.deepEqual(g.frame(12n, false, 1100), { decode: false, resume: false, request: true });
  assert.deepEqual(g.frame(13n, true, 1133), { decode: true, resume: true, request: false });
  assert.deepEqual(g.stats, { received: 8, submitted: 3, skipped: 5, gaps: 1, broken: 1, requests: 3 });
});

test("a gap that lands on a keyframe costs no request; a replayed old frame breaks the chain", () => {
  const g = new VideoGate();
  g.frame(1n, true, 0);
  // Decoding restarts at that keyframe (the page resets its decoder), nothing is skipped.
  assert.deepEqual(g.frame(3n, true, 10), { decode: true, resume: true, request: false });
  assert.equal(g.frame(2n, false, 20).decode, false);
  assert.equal(g.stats.gaps, 2);
});

test("decoder errors and a full decode queue stop decoding; unsupported stops for good", () => {
  const g = new VideoGate({ requestIntervalMs: 500 });
  g.frame(1n, true, 0);
  assert.equal(g.broken("error", 10), true);
  assert.equal(g.frame(2n, false, 20).decode, false);
  assert.equal(g.frame(3n, true, 30).resume, true);
  assert.equal(g.broken("behind", 40), false, "within 0.5 s of the last request");
  const u = new VideoGate();
  assert.equal(u.broken("unsupported", 0), false);
  assert.deepEqual(u.frame(1n, true, 1000), { decode: false, resume: false, request: false });
  // seq 0: the sender does not number frames, so no gap can be seen.
  const z = new VideoGate();
  z.frame(0n, true, 0);
  assert.equal(z.frame(0n, false, 1).decode, true);
});
