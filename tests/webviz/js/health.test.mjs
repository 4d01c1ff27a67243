import { test } from "node:test";
import assert from "node:assert/strict";
import { LinkHealth } from "../../../fleetctl/webviz/static/js/health.js";
import { Rules } from "../../../fleetctl/webviz/static/js/rules.js";
import { reEscape, wantedRegexes } from "../../../fleetctl/webviz/static/js/panels.js";
import { ago, batteryText, breakable, duration, robotRow, toEpochS } from "../../../fleetctl/webviz/static/js/views/overview.js";
import { cloudXYZ } from "../../../fleetctl/webviz/static/js/views/cloudpoints.js";

test("seq gaps count as drops; rate and latency over the window", () => {
  const h = new LinkHealth();
  const now = 1_700_000_000_000;
  for (const [seq, i] of [[1, 0], [2, 1], [5, 2], [6, 3]]) {
    h.record({ topic: "/r/scan", seq: BigInt(seq), publish_time_ns: BigInt(now + i * 100 - 20) * 1000000n }, 10, now + i * 100);
  }
  const [row] = h.rows("/r/", now + 400);
  assert.equal(row.drops, 2);
  assert.equal(row.received, 4);
  assert.equal(row.rateHz, 4); // younger than the window and than 1 s: 4 messages, at most 4/s
  assert.equal(row.latencyMs, 20);
  assert.deepEqual(h.rows("/other/", now), []);
});

test("a young topic's rate is over the time seen, then over the window", () => {
  // A 1 Hz status read 0.2, 0.4, 0.6 ... msg/s for the page's first five seconds.
  const h = new LinkHealth();
  const now = 1_700_000_000_000;
  const rate = (t) => h.rows("/r/", now + t)[0].rateHz;
  const rec = (t) => h.record({ topic: "/r/status", seq: BigInt(t / 1000 + 1), publish_time_ns: 0n }, 10, now + t);
  rec(0);
  assert.equal(rate(500), 1 / 5); // one message: no rate yet but the window's
  rec(1000);
  assert.equal(rate(1000), 1);
  rec(2000);
  assert.equal(rate(2000), 1);
  assert.equal(rate(2500), 0.8); // it decays if the topic stops
  for (let t = 3000; t <= 9000; t += 1000) rec(t);
  assert.equal(rate(9000), 6 / 5); // the window is full: the 6 messages of [4, 9] s
  assert.equal(rate(20000), 0);
});

test("a topic is stale after 5 of its periods, at least 3 s; a panel when all its judged topics are", () => {
  const h = new LinkHealth();
  const now = 1_700_000_000_000;
  const rec = (topic, t, latched = false) => h.record({ topic, seq: 0n, latched, publish_time_ns: 0n }, 10, now + t);
  for (let t = 0; t <= 1000; t += 100) rec("/r/scan", t); // 10 Hz
  for (let t = 0; t <= 4000; t += 1000) rec("/r/status", t); // 1 Hz
  rec("/r/map", 0, true); // latched, once: never judged
  rec("/r/map", 500); // one live message: no period yet
  const f = (topics, t) => h.freshness(topics, now + t);
  assert.deepEqual(f(["/r/scan"], 3900), { stale: false, lastMs: now + 1000 }); // 2.9 s: the 3 s floor
  assert.deepEqual(f(["/r/scan"], 4100), { stale: true, lastMs: now + 1000 });
  assert.equal(f(["/r/status"], 8900).stale, false); // 4.9 s: five 1 s periods not yet
  assert.equal(f(["/r/status"], 9100).stale, true);
  // The newest of a panel's judged topics counts; one fresh topic keeps the panel fresh.
  assert.deepEqual(f(["/r/scan", "/r/status", "/r/map"], 5000), { stale: false, lastMs: now + 4000 });
  assert.deepEqual(f(["/r/scan", "/r/status", "/r/map"], 9100), { stale: true, lastMs: now + 4000 });
  // Nothing judged (a map sent once, a topic never seen): not stale, no time.
  assert.deepEqual(f(["/r/map", "/r/gps/fix"], 60_000), { stale: false, lastMs: null });
  // A topic that resumes is fresh at once.
  rec("/r/scan", 20_000);
  assert.equal(f(["/r/scan"], 20_100).stale, false);
});

test("a long robot name may wrap after its separators, and stays escaped", () => {
  assert.equal(breakable("north_07.a-b/c"), "north_<wbr>07.<wbr>a-<wbr>b/<wbr>c");
  assert.equal(breakable("<r&1>"), "&lt;r&amp;1&gt;");
});

test("durations and ages in words", () => {
  assert.equal(duration(3.4), "3 s");
  assert.equal(duration(150), "3 min");
  assert.equal(duration(3 * 3600), "3 h");
  assert.equal(ago(100, 101), "now");
  assert.equal(ago(100, 130), "30 s ago");
  assert.equal(ago(NaN, 130), "never");
});

test("a latched message the server kept starts no sequence", () => {
  const h = new LinkHealth();
  const now = 1_700_000_000_000;
  const rec = (seq, latched) => h.record({ topic: "/r/tf", seq: BigInt(seq), latched, publish_time_ns: 0n }, 10, now);
  rec(100, true); // the TF snapshot kept since seq 100
  rec(150, false); // the live stream goes on from 150
  rec(151, false);
  rec(152, true); // a snapshot amid the live ones
  rec(153, false);
  rec(120, true); // the kept snapshot again after a reconnect
  rec(154, false);
  assert.equal(h.rows("/r/", now)[0].drops, 0);
  rec(157, false);
  assert.equal(h.rows("/r/", now)[0].drops, 2);
});

test("rules: full match, op both, unparseable regex grants nothing", () => {
  const r = new Rules([{ topic: "/r1/.*", op: "receive" }, { topic: "/r1/goal_pose", op: "both" }, { topic: "(?P<x>", op: "send" }]);
  assert.ok(r.canReceive("/r1/scan"));
  assert.ok(!r.canSend("/r1/scan"));
  assert.ok(r.canSend("/r1/goal_pose"));
  assert.ok(!r.canSend("/r1/goal_pose2"));
  assert.ok(!r.canReceive("x/r1/scan"));
});

test("subscriptions: only visible panels, topic names escaped", () => {
  assert.equal(reEscape("/a.b/c+d"), "/a\\.b/c\\+d");
  const w = wantedRegexes("r1", new Set(["scan"]));
  assert.deepEqual([...w], ["/r1/scan"]);
  assert.ok(wantedRegexes("r1", new Set(["map"])).has("/r1/pose"));
});

test("overview rows from partial registry entries", () => {
  assert.equal(toEpochS(1_700_000_000), 1_700_000_000);
  assert.equal(toEpochS(1_700_000_000_000), 1_700_000_000);
  assert.equal(toEpochS("2023-11-14T22:13:20Z"), 1_700_000_000);
  const row = robotRow({ name: "a", online: false, last_seen_s: 5, status: null, battery_level: 0.2 }, undefined);
  assert.equal(row.online, false);
  assert.equal(row.lastSeenS, 5);
  assert.equal(row.battery, 0.2);
  assert.equal(row.status, "");
  const live = robotRow({ name: "b", online: true, status: "old" }, { status: "ok", is_ok: true, battery_level: 0.5, location: "x" });
  assert.equal(live.battery, 0.5);
  assert.equal(live.status, "ok");
});

test("battery column: a fraction as percent, unknown (-1 from a robot without battery_topic) as a dash", () => {
  assert.equal(batteryText(0.42), "42%");
  assert.equal(batteryText(1), "100%");
  assert.equal(batteryText(0), "0%");
  assert.equal(batteryText(87), "87%");
  assert.equal(batteryText(-1), "–");
  assert.equal(batteryText(undefined), "–");
  assert.equal(batteryText(NaN), "–");
});

test("point cloud extraction decimates and handles unaligned data", () => {
  const n = 1000;
  const f32 = new Float32Array(n * 4);
  for (let i = 0; i < n; i++) f32.set([i, -i, i / 2, 7], 4 * i);
  const fields = ["x", "y", "z"].map((name, i) => ({ name, offset: 4 * i, datatype: 7, count: 1 }));
  const msg = { fields, point_step: 16, width: n, height: 1, is_bigendian: false, data: new Uint8Array(f32.buffer) };
  const a = cloudXYZ(msg, 100);
  assert.equal(a.n, 100);
  assert.deepEqual([...a.xyz.slice(3, 6)], [10, -10, 5]);
  const shifted = new Uint8Array(f32.byteLength + 1);
  shifted.set(new Uint8Array(f32.buffer), 1);
  const b = cloudXYZ({ ...msg, data: shifted.subarray(1) }, 100);
  assert.deepEqual([...b.xyz], [...a.xyz]);
});
