// A navigation goal or initial pose typed or keyed instead of dragged (docs/webviz.md,
// "Commands"): reading the form's x, y (m) and yaw (degrees), the arrow and Q/E keys on
// the focused map, and what the form starts with. Pure: no DOM; app.js and views/map.js
// act. A typed pose is sent by the same function as a dragged one (App.sendPose), so the
// message, topic, frame, stamp and ACL check are the drag's.

// Why a bound: a map 100 km across is not a robot's; 1e12 typed for 1.2 is a typo that
// would send the robot's planner a goal it can only fail on.
export const MAX_ABS_M = 100000;
export const STEP_M = 0.1; // an arrow key; with Shift, BIG_STEP_M
export const BIG_STEP_M = 1.0;
export const STEP_DEG = 5; // Q / E; with Shift, BIG_STEP_DEG
export const BIG_STEP_DEG = 45;

const NUMBER = /^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$/;
const UNITS = { x: "metres", y: "metres", yaw: "degrees" };

/**
 * One field's number: a decimal ("12.5", "-3", "1e2"), finite and within bounds. A comma
 * is refused, not read: "12,5" is 12.5 on one keyboard and "1,000" is 1000 on another, and
 * a goal read the wrong way sends a robot somewhere else.
 * @returns {{value: number}|{error: string}} error: what is wrong, in words, naming the field
 */
export function parseField(name, text) {
  const raw = String(text ?? "").trim();
  const example = name === "yaw" ? "180" : "12.5";
  if (raw === "") return { error: `${name} is empty: type a number of ${UNITS[name]} (e.g. ${example})` };
  if (/^[+-]?[\d,]*,[\d,]*$/.test(raw)) {
    return { error: `${name}: "${raw.slice(0, 20)}" has a comma: write the decimal point as "." (e.g. ${example})` };
  }
  if (!NUMBER.test(raw)) return { error: `${name}: "${raw.slice(0, 20)}" is not a number of ${UNITS[name]} (e.g. ${example})` };
  const value = Number(raw);
  if (!Number.isFinite(value)) return { error: `${name}: ${raw.slice(0, 20)} is too large to be a number` };
  if (name !== "yaw" && Math.abs(value) > MAX_ABS_M) {
    return { error: `${name}: ${raw.slice(0, 20)} m is more than ${MAX_ABS_M / 1000} km from the frame's origin` };
  }
  return { value };
}

/**
 * The pose a form's three fields say.
 * @param {{x: string, y: string, yaw: string}} fields the texts typed
 * @returns {{pose: {x: number, y: number, yaw: number}}|{field: string, error: string}}
 *   pose: metres and radians, yaw in (-pi, pi]; else the first bad field and why
 */
export function parsePose(fields) {
  const values = {};
  for (const name of ["x", "y", "yaw"]) {
    const got = parseField(name, fields[name]);
    if ("error" in got) return { field: name, error: got.error };
    values[name] = got.value;
  }
  return { pose: { x: values.x, y: values.y, yaw: normalizeRad((values.yaw * Math.PI) / 180) } };
}

/** An angle in (-pi, pi]. */
export function normalizeRad(rad) {
  const r = rad - 2 * Math.PI * Math.floor((rad + Math.PI) / (2 * Math.PI)); // [-pi, pi)
  return r === -Math.PI ? Math.PI : r;
}

/** The form's texts for a pose (m to 0.01 m, degrees to 0.1°, "-0" written as "0"). */
export function formatPose({ x, y, yaw }) {
  const fixed = (v, digits) => (Math.abs(v) < 0.5 * 10 ** -digits ? 0 : v).toFixed(digits);
  return { x: fixed(x, 2), y: fixed(y, 2), yaw: fixed((normalizeRad(yaw) * 180) / Math.PI, 1) };
}

/**
 * What the form starts with: the last pose of this kind sent from this page (a drag
 * included: correcting it is the usual next step), else where the robot is now, else the
 * middle of the map shown, heading 0.
 */
export function initialPose(lastSent, robot, center) {
  if (lastSent) return { x: lastSent.x, y: lastSent.y, yaw: lastSent.yaw };
  if (robot) return { x: robot.x, y: robot.y, yaw: robot.yaw };
  return { x: center.x, y: center.y, yaw: 0 };
}

/**
 * A key on the focused map with a tool armed: the pose moved (arrows, in the map's frame:
 * up is +y) or turned (Q counter-clockwise, E clockwise), or null for a key that is not one
 * of these (the browser keeps it).
 */
export function keyedPose(pose, key, shift) {
  const m = shift ? BIG_STEP_M : STEP_M;
  const rad = ((shift ? BIG_STEP_DEG : STEP_DEG) * Math.PI) / 180;
  const moves = { ArrowUp: [0, m, 0], ArrowDown: [0, -m, 0], ArrowLeft: [-m, 0, 0], ArrowRight: [m, 0, 0],
                  q: [0, 0, rad], Q: [0, 0, rad], e: [0, 0, -rad], E: [0, 0, -rad] };
  const move = moves[key];
  if (!move) return null;
  return { x: pose.x + move[0], y: pose.y + move[1], yaw: normalizeRad(pose.yaw + move[2]) };
}
