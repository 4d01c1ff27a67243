// The map panel's scale bar (a round length that fits, labelled in m or cm), and the 3D
// scene's odometry trail broken at jumps as the map panel's path is.
import { test } from "node:test";
import assert from "node:assert/strict";
import { scaleBar } from "../../../fleetctl/webviz/static/js/views/map.js";
import { pathSegments } from "../../../fleetctl/webviz/static/js/views/sceneobjects.js";

test("the scale bar is the longest 1, 2 or 5 x 10^k m that fits", () => {
  assert.deepEqual(scaleBar(40), { m: 2, px: 80, label: "2 m" }); // the default 40 px/m: 3 m fit
  assert.deepEqual(scaleBar(24), { m: 5, px: 120, label: "5 m" }); // exactly 120 px
  assert.deepEqual(scaleBar(2), { m: 50, px: 100, label: "50 m" }); // zoomed all the way out
  assert.equal(scaleBar(400).label, "20 cm"); // all the way in: 0.3 m fit
  assert.equal(scaleBar(1000).label, "10 cm");
  for (let pxPerM = 2; pxPerM <= 400; pxPerM *= 1.2) {
    const bar = scaleBar(pxPerM);
    assert.ok(bar.px <= 120 + 1e-6 && bar.px > 120 / 5 - 1e-6, `${pxPerM}: ${bar.px}`);
  }
});

test("a driven path has no segment across a jump (the scene's odometry trail)", () => {
  const p = (x, y = 0) => ({ x, y, z: 0 });
  const path = [p(0), p(0.5), p(1.0), p(4.0), p(4.5)]; // data missing while the robot drove 3 m
  assert.deepEqual(pathSegments(path), [p(0), p(0.5), p(0.5), p(1.0), p(4.0), p(4.5)]);
  assert.deepEqual(pathSegments([p(0)]), []);
  assert.deepEqual(pathSegments([p(0), p(0.6, 0.8)]), [p(0), p(0.6, 0.8)]); // exactly 1 m: driven
});
