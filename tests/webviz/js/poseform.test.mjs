// A pose typed or keyed instead of dragged (docs/webviz.md, "Commands"): the form's
// numbers, its messages for bad input, what it starts with, and the map's keys.
import { test } from "node:test";
import assert from "node:assert/strict";
import { goalMessage } from "../../../fleetctl/webviz/static/js/commands.js";
import {
  BIG_STEP_M, MAX_ABS_M, formatPose, initialPose, keyedPose, normalizeRad, parseField, parsePose,
} from "../../../fleetctl/webviz/static/js/poseform.js";

const deg = (d) => (d * Math.PI) / 180;

test("a dock typed to the number: x=12.5, y=-3.0, yaw 180°", () => {
  const { pose } = parsePose({ x: " 12.5 ", y: "-3.0", yaw: "180" });
  assert.deepEqual(pose, { x: 12.5, y: -3, yaw: Math.PI });
  // The message a drag to the same pose sends (the same function builds both).
  const msg = goalMessage(pose.x, pose.y, pose.yaw, "map", 1_700_000_000_250);
  assert.deepEqual(msg.pose.position, { x: 12.5, y: -3, z: 0 });
  assert.ok(Math.abs(msg.pose.orientation.z - 1) < 1e-12 && Math.abs(msg.pose.orientation.w) < 1e-12);
  assert.deepEqual(msg.header, { stamp: { sec: 1_700_000_000, nanosec: 250_000_000 }, frame_id: "map" });
});

test("numbers as people type them; yaw wraps to (-180°, 180°]", () => {
  for (const [text, value] of [["4", 4], ["+4", 4], ["-0.5", -0.5], [".5", 0.5], ["5.", 5], ["1e2", 100], ["-1E-1", -0.1]]) {
    assert.deepEqual(parseField("x", text), { value }, text);
  }
  assert.equal(parsePose({ x: "0", y: "0", yaw: "-180" }).pose.yaw, Math.PI);
  assert.ok(Math.abs(parsePose({ x: "0", y: "0", yaw: "450" }).pose.yaw - deg(90)) < 1e-12);
  assert.ok(Math.abs(parsePose({ x: "0", y: "0", yaw: "-90" }).pose.yaw + deg(90)) < 1e-12);
  assert.equal(normalizeRad(-Math.PI), Math.PI);
});

test("bad input: the field, what is wrong and an example; nothing parsed", () => {
  const cases = [
    [{ x: "", y: "1", yaw: "0" }, "x", /^x is empty: type a number of metres \(e\.g\. 12\.5\)$/],
    [{ x: "1", y: "abc", yaw: "0" }, "y", /^y: "abc" is not a number of metres/],
    [{ x: "1", y: "2", yaw: "ninety" }, "yaw", /^yaw: "ninety" is not a number of degrees \(e\.g\. 180\)$/],
    [{ x: "12,5", y: "0", yaw: "0" }, "x", /has a comma: write the decimal point as "\."/],
    [{ x: "1,000", y: "0", yaw: "0" }, "x", /has a comma/],
    [{ x: "NaN", y: "0", yaw: "0" }, "x", /is not a number/],
    [{ x: "Infinity", y: "0", yaw: "0" }, "x", /is not a number/],
    [{ x: "1e400", y: "0", yaw: "0" }, "x", /too large to be a number/],
    [{ x: "0", y: "0", yaw: "1e999" }, "yaw", /too large/],
    [{ x: "0", y: String(MAX_ABS_M + 1), yaw: "0" }, "y", /more than 100 km from the frame's origin/],
    [{ x: "0x10", y: "0", yaw: "0" }, "x", /is not a number/],
    [{ x: "1 2", y: "0", yaw: "0" }, "x", /is not a number/],
  ];
  for (const [fields, field, message] of cases) {
    const got = parsePose(fields);
    assert.equal(got.pose, undefined, JSON.stringify(fields));
    assert.equal(got.field, field, JSON.stringify(fields));
    assert.match(got.error, message);
  }
  // A long paste is cut in the message.
  assert.ok(parseField("x", "z".repeat(500)).error.length < 100);
});

test("the form starts with the last pose sent, else the robot's, else the map's middle", () => {
  const sent = { kind: "goal", x: 4, y: 2, yaw: deg(90) };
  const robot = { x: 1, y: 1, yaw: 0.5 };
  assert.deepEqual(initialPose(sent, robot, { x: 9, y: 9 }), { x: 4, y: 2, yaw: deg(90) });
  assert.deepEqual(initialPose(null, robot, { x: 9, y: 9 }), robot);
  assert.deepEqual(initialPose(null, null, { x: 9, y: 9 }), { x: 9, y: 9, yaw: 0 });
  assert.deepEqual(formatPose({ x: 4, y: -0.0001, yaw: deg(90) }), { x: "4.00", y: "0.00", yaw: "90.0" });
  assert.deepEqual(formatPose({ x: 12.5, y: -3, yaw: -Math.PI }), { x: "12.50", y: "-3.00", yaw: "180.0" });
  // What the form shows reads back as the same pose (to its precision).
  const back = parsePose(formatPose({ x: 1.234, y: -5.678, yaw: deg(-33.3) })).pose;
  assert.ok(Math.abs(back.x - 1.23) < 1e-9 && Math.abs(back.y + 5.68) < 1e-9 && Math.abs(back.yaw - deg(-33.3)) < 1e-9);
});

test("keys on the map: arrows move in the map frame, Q/E turn, Shift for big steps", () => {
  const at = { x: 1, y: 1, yaw: 0 };
  const near = (a, b) => ["x", "y", "yaw"].every((k) => Math.abs(a[k] - b[k]) < 1e-9);
  assert.ok(near(keyedPose(at, "ArrowUp", false), { x: 1, y: 1.1, yaw: 0 }));
  assert.ok(near(keyedPose(at, "ArrowLeft", true), { x: 1 - BIG_STEP_M, y: 1, yaw: 0 }));
  assert.ok(near(keyedPose(at, "q", false), { x: 1, y: 1, yaw: deg(5) }));
  assert.ok(near(keyedPose(at, "E", true), { x: 1, y: 1, yaw: deg(-45) }));
  assert.ok(near(keyedPose({ x: 0, y: 0, yaw: deg(178) }, "q", false), { x: 0, y: 0, yaw: deg(-177) }));
  assert.equal(keyedPose(at, "Tab", false), null); // the browser keeps it: focus moves on
  assert.equal(keyedPose(at, "Enter", false), null);
});
