import { test } from "node:test";
import assert from "node:assert/strict";
import { writeFileSync } from "node:fs";
import { join } from "node:path";
import { Builder } from "../../../fleetctl/webviz/static/js/fb/builder.js";
import { Reader, readMetadata } from "../../../fleetctl/webviz/static/js/fb/reader.js";
import { DIR, HAVE, cases, layoutsFor, mismatch } from "./cases.mjs";
import { goalMessage, initialPoseMessage } from "../../../fleetctl/webviz/static/js/commands.js";

const skip = HAVE ? false : "FLEETCTL_WEBVIZ_CASES not set (run through pytest)";

/** JSON cannot carry 64-bit ints exactly: the harness sends them as {$bigint: text}. */
function prepare(v) {
  if (Array.isArray(v)) return v.map(prepare);
  if (v && typeof v === "object") {
    if ("$bigint" in v) return BigInt(v.$bigint);
    return Object.fromEntries(Object.entries(v).map(([k, x]) => [k, prepare(x)]));
  }
  return v;
}

test("builds every sample; the JS reader reads back the same values", { skip }, () => {
  for (const b of cases.build) {
    const layouts = layoutsFor(b.type);
    const value = prepare(b.value);
    const frame = new Builder(layouts).encode(b.type, {
      __metadata: { type: b.type, topic: b.topic, seq: 9n, publish_time_ns: 1n << 62n },
      ...value,
    });
    // Written for the pytest wrapper, which decodes them with the Python codec.
    writeFileSync(join(DIR, "built", b.name), frame);
    const meta = readMetadata(frame);
    assert.equal(meta.topic, b.topic);
    assert.equal(meta.seq, 9n);
    const expected = cases.decode.find((c) => c.name === b.name.replace("built", "sample")).expected;
    const back = new Reader(layouts).decode(frame, b.type);
    assert.equal(mismatch(back, expected), null, b.type);
  }
});

test("goal and initial pose messages encode with the served layouts", { skip }, () => {
  const goal = goalMessage(1.5, -2, Math.PI / 2, "map", 1700000000250);
  const lg = layoutsFor("geometry_msgs/msg/PoseStamped");
  const f1 = new Builder(lg).encode("geometry_msgs/msg/PoseStamped", { __metadata: { type: "geometry_msgs/msg/PoseStamped", topic: "/r1/goal_pose" }, ...goal });
  const g = new Reader(lg).decode(f1, "geometry_msgs/msg/PoseStamped");
  assert.equal(g.pose.position.x, 1.5);
  assert.equal(g.header.stamp.sec, 1700000000);
  assert.equal(g.header.stamp.nanosec, 250000000);
  assert.ok(Math.abs(g.pose.orientation.z - Math.SQRT1_2) < 1e-12);
  const init = initialPoseMessage(0, 1, 0);
  const li = layoutsFor("geometry_msgs/msg/PoseWithCovarianceStamped");
  const f2 = new Builder(li).encode("geometry_msgs/msg/PoseWithCovarianceStamped", { __metadata: { type: "x", topic: "/r1/initialpose" }, ...init });
  const p = new Reader(li).decode(f2, "geometry_msgs/msg/PoseWithCovarianceStamped");
  assert.equal(p.pose.covariance.length, 36);
  assert.equal(p.pose.covariance[0], 0.25);
});
