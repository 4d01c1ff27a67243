import { test } from "node:test";
import assert from "node:assert/strict";
import { TfTree, normalizeFrame, multiply, transformPoint, matrixOf } from "../../../fleetctl/webviz/static/js/tf.js";

function ts(parent, child, [x, y, z] = [0, 0, 0], yaw = 0) {
  return {
    header: { frame_id: parent, stamp: { sec: 1, nanosec: 0 } },
    child_frame_id: child,
    transform: { translation: { x, y, z }, rotation: { x: 0, y: 0, z: Math.sin(yaw / 2), w: Math.cos(yaw / 2) } },
  };
}

function close(a, b, eps = 1e-9) {
  assert.equal(a.length, b.length);
  a.forEach((v, i) => assert.ok(Math.abs(v - b[i]) < eps, `${a} != ${b} at ${i}`));
}

function robot() {
  const tf = new TfTree();
  // map -> odom: 10 m east, turned 90 degrees; odom -> base_link: 1 m forward.
  tf.update({ transforms: [ts("map", "odom", [10, 0, 0], Math.PI / 2), ts("odom", "base_link", [1, 0, 0])] }, false, 0);
  // base_link -> base_scan: 0.2 m forward, 0.3 m up, mounted backwards (yaw pi).
  tf.update({ transforms: [ts("/base_link", "/base_scan", [0.2, 0, 0.3], Math.PI)] }, true, 0);
  return tf;
}

test("a point in base_scan lands where the chain of transforms puts it in map", () => {
  const tf = robot();
  const r = tf.lookup("map", "base_scan");
  assert.ok(r.ok, r.reason);
  // 1 m ahead of the backwards-mounted scanner is 0.8 m behind... base_link x = 0.2 - 1 = -0.8.
  // In odom: (1 - 0.8, 0) = (0.2, 0, 0.3); map rotates odom by 90 degrees and shifts 10 m east.
  close(transformPoint(r.matrix, [1, 0, 0]), [10, 0.2, 0.3]);
  // The inverse lookup undoes it.
  const back = tf.lookup("base_scan", "map");
  close(transformPoint(back.matrix, [10, 0.2, 0.3]), [1, 0, 0]);
  close(multiply(back.matrix, r.matrix), [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
});

test("frames across branches meet at their common ancestor", () => {
  const tf = robot();
  tf.update({ transforms: [ts("base_link", "camera", [0.5, 0, 0])] }, true, 0);
  const r = tf.lookup("base_scan", "camera");
  assert.ok(r.ok);
  // camera origin is base_link (0.5, 0); base_scan is at (0.2, 0, 0.3) facing backwards.
  close(transformPoint(r.matrix, [0, 0, 0]), [-0.3, 0, -0.3]);
});

test("leading slashes are stripped from frame names", () => {
  assert.equal(normalizeFrame("/map"), "map");
  assert.equal(normalizeFrame("//odom"), "odom");
  assert.equal(normalizeFrame("base_link"), "base_link");
  const tf = robot();
  assert.ok(tf.lookup("/map", "/base_scan").ok);
  assert.ok(tf.has("base_scan") && tf.has("/base_scan"));
});

test("a broken chain says which frame lacks a parent", () => {
  const tf = new TfTree();
  tf.update({ transforms: [ts("base_link", "base_scan", [0.2, 0, 0])] }, true, 0);
  tf.update({ transforms: [ts("map", "odom")] }, false, 0);
  const r = tf.lookup("map", "base_scan");
  assert.equal(r.ok, false);
  assert.equal(r.reason, "no path from base_scan to map: base_link has no parent");
  assert.equal(tf.lookup("map", "lidar").reason, "no path from lidar to map: lidar is not in the TF tree");
  assert.equal(tf.lookup("map", "").reason, "no path from (empty) to map: the message has no frame_id");
  // odom -> base_link arrives: the chain is whole.
  tf.update({ transforms: [ts("odom", "base_link", [1, 0, 0])] }, false, 0);
  close(transformPoint(tf.lookup("map", "base_scan").matrix, [0, 0, 0]), [1.2, 0, 0]);
});

test("the latest transform of an edge wins (no interpolation)", () => {
  const tf = robot();
  const v = tf.version;
  tf.update({ transforms: [ts("odom", "base_link", [2, 0, 0])] }, false, 5);
  assert.ok(tf.version > v);
  close(transformPoint(tf.lookup("odom", "base_link").matrix, [0, 0, 0]), [2, 0, 0]);
});

test("cycles, self edges, non-finite numbers and too many frames are refused and counted", () => {
  const tf = robot();
  assert.equal(tf.update({ transforms: [ts("base_scan", "map")] }, false, 0), 0);
  assert.equal(tf.stats.refusedCycle, 1);
  assert.equal(tf.update({ transforms: [ts("a", "a"), ts("a", "b", [NaN, 0, 0]), ts("", "c")] }, false, 0), 0);
  assert.equal(tf.stats.refusedBad, 3);
  assert.ok(tf.lookup("map", "base_scan").ok, "the tree is unchanged by refusals");
  const small = new TfTree({ maxFrames: 3 });
  assert.equal(small.update({ transforms: [ts("a", "b"), ts("b", "c"), ts("c", "d")] }, false, 0), 2);
  assert.equal(small.stats.refusedFull, 1);
  assert.equal(small.problems.length, 1);
});

test("fixed frame: map, else odom, else the root of the biggest tree, else none", () => {
  assert.deepEqual(robot().fixedFrame(), { frame: "map", why: "map" });
  const odom = new TfTree();
  odom.update({ transforms: [ts("odom", "base_link")] }, false, 0);
  assert.equal(odom.fixedFrame().frame, "odom");
  const other = new TfTree();
  other.update({ transforms: [ts("world", "base"), ts("base", "arm"), ts("x", "y")] }, false, 0);
  assert.equal(other.fixedFrame().frame, "world");
  assert.equal(other.fixedFrame("arm").frame, "arm");
  assert.equal(new TfTree().fixedFrame().frame, null);
});

test("rows list the tree depth first with static flags and ages", () => {
  const tf = robot();
  const rows = tf.rows(1000);
  assert.deepEqual(rows.map((r) => [r.frame, r.depth, r.isStatic]), [
    ["map", 0, false], ["odom", 1, false], ["base_link", 2, false], ["base_scan", 3, true],
  ]);
  assert.equal(rows[1].ageMs, 1000);
  assert.equal(rows[1].parent, "map");
});

test("matrixOf normalizes the quaternion and matches three.js's column-major layout", () => {
  const m = matrixOf({ x: 1, y: 2, z: 3 }, { x: 0, y: 0, z: 2, w: 0 }); // 180 degrees about z, unnormalized
  close([...m], [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 1, 2, 3, 1]);
});
