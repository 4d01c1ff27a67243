// Which robots of the registry are `fleetctl replay`'s renamed recordings (husky1_replay),
// by the rule of fleetctl status, less its fleet.yaml check (the page has no fleet.yaml).
import { test } from "node:test";
import assert from "node:assert/strict";
import { replayOf } from "../../../fleetctl/webviz/static/js/replays.js";
import { robotRow } from "../../../fleetctl/webviz/static/js/views/overview.js";

test("a name ending in _replay is a replay of the name before it", () => {
  assert.equal(replayOf("husky1_replay"), "husky1");
  assert.equal(replayOf("husky1_replay_replay"), "husky1_replay"); // a replay of a replay
});

test("other names are no replay", () => {
  for (const name of ["husky1", "_replay", "replay", "husky1_replayed", "husky1-replay", "", undefined, null, 7]) {
    assert.equal(replayOf(name), null, String(name));
  }
});

test("the overview row carries what it replays", () => {
  assert.equal(robotRow({ name: "husky1_replay", online: true }).replayOf, "husky1");
  assert.equal(robotRow({ name: "husky1", online: true }).replayOf, null);
});
