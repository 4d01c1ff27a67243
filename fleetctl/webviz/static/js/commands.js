// Messages the page sends to a robot (docs/design.md section 7): a navigation goal on
// /<robot>/goal_pose and an initial pose on /<robot>/initialpose.

export const GOAL = { suffix: "/goal_pose", type: "geometry_msgs/msg/PoseStamped", label: "navigation goal" };
export const INITIAL = { suffix: "/initialpose", type: "geometry_msgs/msg/PoseWithCovarianceStamped", label: "initial pose" };

function header(frameId, nowMs) {
  return { stamp: { sec: Math.floor(nowMs / 1000), nanosec: (nowMs % 1000) * 1e6 }, frame_id: frameId };
}

function pose(x, y, yaw) {
  return { position: { x, y, z: 0 }, orientation: { x: 0, y: 0, z: Math.sin(yaw / 2), w: Math.cos(yaw / 2) } };
}

export function goalMessage(x, y, yaw, frameId = "map", nowMs = Date.now()) {
  return { header: header(frameId, nowMs), pose: pose(x, y, yaw) };
}

export function initialPoseMessage(x, y, yaw, frameId = "map", nowMs = Date.now()) {
  // 0.5 m and ~15 degrees standard deviation, as rviz's "2D Pose Estimate" tool sends.
  const covariance = new Float64Array(36);
  covariance[0] = 0.25;
  covariance[7] = 0.25;
  covariance[35] = 0.06853891909122467;
  return { header: header(frameId, nowMs), pose: { pose: pose(x, y, yaw), covariance } };
}
