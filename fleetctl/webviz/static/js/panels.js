// What a robot page shows: each panel, the robot-relative topics it subscribes to while
// visible, and which message types it draws (`draws`: a panel with one type says, while
// it has drawn nothing, which topic it waits for). Topic names follow docs/design.md section 7.

export const PANELS = [
  // The scene asks for the viewer form of the cloud only; the full cloud arrives (and is
  // drawn in the scene too) while the Cloud panel is shown.
  { id: "scene", title: "3D scene (TF)", topics: ["/tf", "/tf_static", "/scan", "/points/viewer", "/odom", "/pose", "/plan", "/markers", "/marker", "/map"] },
  // CompressedVideo on any subscribed topic goes to the video panel (a CompressedImage topic
  // configured as video keeps its name, and the Camera panel subscribes it).
  { id: "video", title: "Video", topics: ["/camera/image_raw", "/camera/image", "/camera/video"] },
  { id: "camera", title: "Camera", topics: ["/camera/image/compressed"], draws: "sensor_msgs/msg/CompressedImage" },
  { id: "scan", title: "Laser scan", topics: ["/scan"], draws: "sensor_msgs/msg/LaserScan" },
  { id: "cloud", title: "Point cloud", topics: ["/points"], draws: "sensor_msgs/msg/PointCloud2" },
  { id: "map", title: "Map, pose, path, markers", topics: ["/pose", "/odom", "/map", "/plan", "/markers", "/marker"] },
  { id: "odom", title: "Odometry", topics: ["/odom"], draws: "nav_msgs/msg/Odometry" },
  { id: "gps", title: "GPS", topics: ["/gps/fix"], draws: "sensor_msgs/msg/NavSatFix" },
];

/** Escape a topic name so it is a literal in an RE2 (and JS) regex. */
export function reEscape(s) {
  return s.replace(/[.*+?^${}()|[\]\\]/g, "\\$&");
}

/** Regexes to subscribe to for the visible panels of one robot. */
export function wantedRegexes(robot, visibleIds) {
  const out = new Set();
  for (const p of PANELS) {
    if (!visibleIds.has(p.id)) continue;
    for (const t of p.topics) out.add(reEscape(`/${robot}${t}`));
  }
  return out;
}
