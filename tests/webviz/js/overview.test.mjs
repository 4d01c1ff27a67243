// The fleet table's rows: a robot of the auth map the server has never heard from
// (GET /robots and list_robots mark it never_connected) reads "never connected", not
// "offline" as if it had been online once.
import { test } from "node:test";
import assert from "node:assert/strict";
import { renderOverview, robotRow } from "../../../fleetctl/webviz/static/js/views/overview.js";

const NEVER = {
  name: "husky2", online: false, never_connected: true, first_seen_s: null,
  last_seen_s: null, status: null, is_ok: null, battery_level: null, location: null,
};

function rendered(entries) {
  const tbody = { innerHTML: "" };
  renderOverview(tbody, entries.map((e) => robotRow(e, undefined)), () => "–");
  return tbody.innerHTML;
}

test("a robot never connected says so, with no last-seen time", () => {
  const html = rendered([NEVER]);
  assert.match(html, /<td class="state nowrap">never connected<\/td>/);
  assert.match(html, /<td class="nowrap">never<\/td>/); // last seen
  assert.doesNotMatch(html, /NaN|null|undefined/);
});

test("a robot seen before and gone is offline", () => {
  const html = rendered([{ name: "husky1", online: false, last_seen_s: 1_700_000_000 }]);
  assert.match(html, /<td class="state nowrap">offline<\/td>/);
  assert.equal(robotRow({ name: "husky1", online: true }).neverConnected, false);
});
