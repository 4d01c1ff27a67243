// `fleetctl replay` sends a recording's /husky1/... as /husky1_replay/... so no live robot
// acts on last week's goals (docs/server.md, "Replaying onto live robots"); the registry
// then lists husky1_replay, which the page showed as one more live robot.
//
// The rule is `fleetctl status`'s (fleetctl/deploy/replaynames.py) less its fleet.yaml
// check: the page knows the relay's registry, not the fleet. So a fleet robot whose own
// name ends in _replay is marked too (docs/webviz.md, "Replays"); that is why the page only
// labels a replay and its command tools, and never takes them away.

export const REPLAY_SUFFIX = "_replay";

/** The recorded robot a registry name replays ("husky1_replay" -> "husky1"), or null. */
export function replayOf(name) {
  if (typeof name !== "string" || !name.endsWith(REPLAY_SUFFIX)) return null;
  return name.slice(0, -REPLAY_SUFFIX.length) || null;
}
