// DrawPacer: an expensive canvas's draws take at most a share of the main thread, learned
// from the animation frame's interval after each draw; a cheap draw never waits.
import { test } from "node:test";
import assert from "node:assert/strict";
import { DrawPacer } from "../../../fleetctl/webviz/static/js/drawpacer.js";

const FRAME = 1000 / 60;

/** Frames of *frameMs* each for *ms*, drawing whenever the pacer lets; returns the draws. */
function run(pacer, { ms, drawCostMs, from = 0 }) {
  let now = from;
  let draws = 0;
  let busy = 0;
  while (now < from + ms) {
    if (pacer.due(now)) {
      pacer.drew(now);
      draws++;
      busy += drawCostMs;
      now += FRAME + drawCostMs; // the draw's frame lasts its cost longer
    } else {
      pacer.defer();
      now += FRAME;
    }
  }
  return { draws, busyShare: busy / (now - from), end: now };
}

test("a cheap draw is never put off: one draw per display frame", () => {
  const pacer = new DrawPacer();
  const { draws } = run(pacer, { ms: 1000, drawCostMs: 0 });
  assert.ok(draws >= 59, `${draws} draws in 1 s`);
  assert.equal(pacer.deferred, 0);
});

test("a 100 ms draw takes about half the main thread, not all of it", () => {
  const pacer = new DrawPacer(0.5);
  const { draws, busyShare } = run(pacer, { ms: 10_000, drawCostMs: 100 });
  assert.ok(busyShare > 0.4 && busyShare <= 0.55, `draws took ${(busyShare * 100).toFixed(0)} %`);
  assert.ok(draws >= 40 && draws <= 55, `${draws} draws in 10 s`);
  assert.ok(pacer.deferred > 0);
  // Without the pacer the same draws would take 100 ms of every 117 ms frame.
});

test("a smaller share waits longer between draws", () => {
  const { busyShare } = run(new DrawPacer(0.25), { ms: 10_000, drawCostMs: 100 });
  assert.ok(busyShare > 0.18 && busyShare <= 0.3, `draws took ${(busyShare * 100).toFixed(0)} %`);
});

test("a hidden tab's long gap is not taken for a draw's cost", () => {
  const pacer = new DrawPacer();
  pacer.due(0);
  pacer.drew(0);
  assert.equal(pacer.due(60_000), true); // the tab came back after a minute: draw at once
  assert.equal(pacer.costMs, 0);
});

test("the cost follows the machine: draws get cheap again, the wait goes", () => {
  const pacer = new DrawPacer();
  const { end } = run(pacer, { ms: 5000, drawCostMs: 200 });
  assert.ok(pacer.costMs > 150, `cost ${pacer.costMs}`);
  run(pacer, { ms: 5000, drawCostMs: 0, from: end });
  assert.ok(pacer.costMs < 1, `cost ${pacer.costMs}`);
});

test("a share outside (0, 1] is refused", () => {
  assert.throws(() => new DrawPacer(0), RangeError);
  assert.throws(() => new DrawPacer(1.5), RangeError);
});
