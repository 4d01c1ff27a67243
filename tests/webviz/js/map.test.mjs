// The map panel's scale bar (a round length that fits, labelled in m or cm), and the 3D
// scene's odometry trail broken at jumps as the map panel's path is; the GPS readout.
import { test } from "node:test";
import assert from "node:assert/strict";
import { scaleBar } from "../../../fleetctl/webviz/static/js/views/map.js";
import { pathSegments } from "../../../fleetctl/webviz/static/js/views/sceneobjects.js";
import { fixText } from "../../../fleetctl/webviz/static/js/views/gps.js";

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

test("a GPS fix in words with units, and its accuracy when the covariance is known", () => {
  const fix = (status, type, cov = [0, 0, 0, 0, 0, 0, 0, 0, 0]) => ({
    latitude: 30.2862, longitude: -97.7365, altitude: 150, status: { status },
    position_covariance: Float64Array.from(cov), position_covariance_type: type,
  });
  assert.equal(fixText(fix(0, 0)), "lat 30.286200° lon -97.736500° alt 150.0 m, fix");
  assert.equal(fixText(fix(-1, 0)), "lat 30.286200° lon -97.736500° alt 150.0 m, NO FIX");
  assert.equal(fixText(fix(2, 2, [0.04, 0, 0, 0, 2.25, 0, 0, 0, 9])),
    "lat 30.286200° lon -97.736500° alt 150.0 m, GBAS (RTK) fix, ±1.5 m");
  assert.equal(fixText(fix(1, 0, [4, 0, 0, 0, 4, 0, 0, 0, 4])).endsWith("SBAS fix"), true); // unknown covariance
});
