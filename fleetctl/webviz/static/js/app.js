// The page: sign-in, fleet overview, robot pages, commands, health and banner.

import { Connection, layoutsOf } from "./connection.js";
import { STALE_MIN_MS } from "./health.js";
import { LayoutLoader } from "./fb/layout.js";
import { throttledText } from "./loginthrottle.js";
import { mirrorTitles } from "./oneline.js";
import { GOAL, INITIAL, goalMessage, initialPoseMessage } from "./commands.js";
import { PANELS, reEscape, wantedRegexes } from "./panels.js";
import { replayOf } from "./replays.js";
import { CameraView } from "./views/camera.js";
import { CloudView } from "./views/cloud.js";
import { GpsView } from "./views/gps.js";
import { MapView } from "./views/map.js";
import { OdomView } from "./views/odom.js";
import { PoseTools } from "./views/posetools.js";
import { ago, duration, renderOverview, robotRow, toEpochS } from "./views/overview.js";
import { ScanView } from "./views/scan.js";
import { SceneView } from "./views/scene.js";
import { VideoView } from "./views/video.js";

const $ = (sel) => document.querySelector(sel);
const ROBOTS_POLL_MS = 2000;
const STATUS_TYPE = "amrl_msgs/msg/RobofleetStatus";
const VIDEO_TYPE = "foxglove_msgs/msg/CompressedVideo";
const BEHIND_MS = 1000; // median latency above which the page says its data is old
// The control topic a viewer asks a video's publisher for a keyframe on (docs/server.md).
export const KEYFRAME_REQUEST = { type: "fleetctl_msgs/msg/KeyframeRequest", topic: "/keyframe_requests" };

class App {
  constructor(config) {
    this.config = config;
    this.registry = [];
    this.registryKnown = false; // a robots list arrived since sign-in
    this.liveStatus = new Map();
    this.robot = null; // robot whose page is open
    this.visible = new Set(PANELS.map((p) => p.id));
    this.paused = false;
    this.poseSeenMs = 0;
    this.frameId = "map";
    this.keyframeRequests = { sent: 0, failed: 0, last: null };
    this.seenTypes = new Map(); // topic -> type of the last message of the open robot
  }

  signIn(token) {
    this.conn?.stop();
    const failoverUrls = this.config.failover_urls ?? [];
    // With replicas, layouts come from the replica the page is connected to now: the
    // page's own origin may be the replica that went away.
    const layoutBase = failoverUrls.length ? () => layoutsOf(conn.url) : "types/";
    const conn = new Connection({ url: this.config.server_url, failoverUrls, token: token || null, loader: new LayoutLoader(layoutBase) });
    this.conn = conn;
    conn.addEventListener("status", (e) => this.onStatus(e.detail));
    conn.addEventListener("welcome", () => this.onWelcome());
    conn.addEventListener("robots", (e) => this.onRobots(e.detail));
    conn.addEventListener("message", (e) => this.onMessage(e.detail));
    conn.addEventListener("server-error", (e) => this.onServerError(e.detail));
    conn.addEventListener("unsupported", () => this.renderNotes());
    conn.start();
    // A new session: the last one's server messages (a refused token's bad_token) stayed
    // listed under the fleet after a good sign-in, as if something were wrong now.
    $("#errors").replaceChildren();
    $("#signin").hidden = true;
    $("#main").hidden = false;
    $("#signout").hidden = false; // before a sign-in it signed nobody out
    clearInterval(this.poll);
    this.poll = setInterval(() => conn.listRobots(), ROBOTS_POLL_MS);
    this.route();
  }

  onStatus({ state, detail, retryMs }) {
    if (this.robot) this.renderRobotState();
    const banner = $("#banner");
    banner.dataset.state = state;
    $("#conn-state").textContent = state;
    if (state === "open") {
      banner.hidden = true;
      this.lastDrop = null;
      return;
    }
    if (state === "disconnected") this.lastDrop = detail;
    banner.hidden = false;
    // While the next attempt waits (an unanswered upgrade takes up to 15 s), the banner
    // keeps why the last connection went; it flashed by in the 0.25 s before the attempt.
    const why = this.lastDrop ? ` (the last connection: ${this.lastDrop})` : "";
    banner.textContent = {
      connecting: `Connecting to ${this.conn?.url ?? this.config.server_url} …${why}`,
      disconnected: `Disconnected from the fleet server (${detail}). Reconnecting in about ${(retryMs / 1000).toFixed(1)} s …`,
      refused: `Signed out: ${detail}. Check your token and sign in again.`,
      throttled: throttledText(retryMs),
      closed: "Connection closed.",
    }[state] ?? state;
    if (state === "refused") {
      clearInterval(this.poll);
      // Only the form: an empty fleet table and robot panels under it read as a fleet
      // with no robots, or as data still coming in.
      $("#main").hidden = true;
      $("#signin").hidden = false;
      $("#signin-error").textContent = detail;
    }
  }

  onWelcome() {
    const ids = this.conn.identities.map((i) => i.name ?? i).join(", ");
    $("#identity").textContent = ids ? `signed in as ${ids}` : "signed in";
    this.conn.listRobots();
    this.updateCommands();
  }

  onRobots(robots) {
    this.registry = robots;
    this.registryKnown = true;
    if (this.robot) this.renderRobotState();
    for (const r of robots) {
      if (r.name) this.conn.subscribe(reEscape(`/${r.name}/status`));
    }
    this.renderOverview();
  }

  renderOverview() {
    const rows = this.registry.map((e) => robotRow(e, this.liveStatus.get(e.name)));
    const link = (name) => {
      const hs = this.conn.health.rows(`/${name}/`);
      if (!hs.length) return "–";
      const rate = hs.reduce((a, h) => a + h.rateHz, 0);
      const lat = hs.map((h) => h.latencyMs).filter(Number.isFinite).sort((a, b) => a - b);
      const drops = hs.reduce((a, h) => a + h.drops, 0);
      return `${rate.toFixed(1)} msg/s, ${lat.length ? lat[lat.length >> 1].toFixed(0) : "–"} ms, ${drops} dropped`;
    };
    renderOverview($("#robots tbody"), rows, link);
    $("#robot-count").textContent = `${rows.length} robot${rows.length === 1 ? "" : "s"}`;
  }

  onMessage({ meta, msg }) {
    if (meta.type === STATUS_TYPE) {
      const name = meta.topic.split("/")[1];
      this.liveStatus.set(name, { status: msg.status, is_ok: msg.is_ok, battery_level: msg.battery_level, location: msg.location });
      return;
    }
    if (!this.robot || !meta.topic.startsWith(`/${this.robot}/`)) return;
    const firstOfType = this.seenTypes.get(meta.topic) !== meta.type;
    this.seenTypes.set(meta.topic, meta.type);
    // A panel's "Nothing on ... yet" goes with its first message, not at the next
    // once-a-second health render: it lay over a camera picture already drawn.
    if (firstOfType) this.renderNotes();
    const v = this.views;
    v.scene.update(meta, msg); // the 3D scene draws what it can place through TF
    switch (meta.type) {
      case VIDEO_TYPE: return v.video.update(meta, msg);
      case "sensor_msgs/msg/CompressedImage": return v.camera.update(msg);
      case "sensor_msgs/msg/LaserScan": return v.scan.update(msg);
      case "sensor_msgs/msg/PointCloud2": return v.cloud.update(msg);
      case "sensor_msgs/msg/NavSatFix": return v.gps.update(msg);
      case "nav_msgs/msg/OccupancyGrid": return v.map.updateGrid(msg);
      case "nav_msgs/msg/Path": return v.map.updatePlan(msg);
      case "visualization_msgs/msg/Marker":
      case "visualization_msgs/msg/MarkerArray": return v.map.updateMarkers(msg);
      case "geometry_msgs/msg/PoseWithCovarianceStamped":
        this.poseSeenMs = Date.now();
        this.frameId = msg.header.frame_id || this.frameId;
        return v.map.updatePose(msg.pose.pose);
      case "nav_msgs/msg/Odometry":
        v.odom.update(msg);
        // Odometry stands in for the pose only while no localization pose arrives.
        if (Date.now() - this.poseSeenMs > 2000) {
          this.frameId = msg.header.frame_id || this.frameId;
          v.map.updatePose(msg.pose.pose);
        }
        return;
      default:
        return;
    }
  }

  onServerError(err) {
    const li = document.createElement("li");
    li.textContent = `${err.code}${err.topic ? ` on ${err.topic}` : ""}: ${err.message ?? ""}`;
    const log = $("#errors");
    log.prepend(li);
    while (log.children.length > 20) log.lastChild.remove();
    if (err.code === "unauthorized_send" && this.robot && err.topic?.startsWith(`/${this.robot}/`)) {
      this.commandStatus(`The server refused: ${err.message ?? "not allowed"} (${err.topic})`, true);
    }
  }

  route() {
    const m = /^#\/robot\/(.+)$/.exec(location.hash);
    const next = m ? decodeURIComponent(m[1]) : null;
    if (this.robot && this.robot !== next) this.setSubscriptions(this.robot, new Set());
    this.robot = next;
    if (!next) $("#behind-note").hidden = true;
    $("#overview").hidden = !!next;
    $("#robot").hidden = !next;
    if (next) this.openRobot(next);
  }

  openRobot(name) {
    $("#robot-name").textContent = name;
    // Views are made once: each owns its canvas (a WebGL context cannot be made twice).
    this.views ??= {
      scene: new SceneView({
        canvas: $("#scene-canvas"), tree: $("#tf-tree"), problems: $("#scene-problems"),
        fixedLabel: $("#scene-fixed"), frameSelect: $("#scene-frame"), axes: $("#scene-axes"),
      }),
      video: new VideoView(
        { canvas: $("#video-canvas"), status: $("#video-status"), select: $("#video-topic") },
        (topic) => this.requestKeyframe(topic),
      ),
      camera: new CameraView($("#camera-canvas")),
      scan: new ScanView($("#scan-canvas")),
      cloud: new CloudView($("#cloud-canvas")),
      map: new MapView($("#map-canvas"), (kind, x, y, yaw) => this.sendPose(kind, x, y, yaw), {
        scale: $("#map-scale"), onAim: (kind, x, y, yaw) => this.tools.onAim(kind, x, y, yaw),
        onKey: (e) => this.tools.onKey(e),
      }),
      odom: new OdomView($("#odom-text")),
      gps: new GpsView($("#gps-map"), $("#gps-text")),
    };
    this.tools ??= new PoseTools({
      map: this.views.map,
      form: {
        form: $("#pose-form"), x: $("#pose-x"), y: $("#pose-y"), yaw: $("#pose-yaw"),
        frame: $("#pose-frame"), error: $("#pose-error"), cancel: $("#pose-cancel"),
      },
      buttons: { goal: $("#tool-goal"), initialpose: $("#tool-initial") },
      say: (text) => this.commandStatus(text),
      send: (kind, x, y, yaw) => this.sendPose(kind, x, y, yaw),
      frameId: () => this.frameId,
    });
    this.tools.cancel(); // a tool armed for the last robot, its form holding that one's pose
    this.views.map.reset();
    if (this.shownRobot !== name) {
      // Another robot: nothing the last one showed is this one's (its camera frame, scan,
      // cloud and odometry stayed on the next robot's page until that one sent its own).
      for (const v of Object.values(this.views)) if (v !== this.views.map) v.reset?.();
      this.seenTypes.clear();
      this.shownRobot = name;
    }
    this.commandStatus("");
    this.renderReplay(name);
    this.renderRobotState();
    this.applyVisibility();
    this.updateCommands();
    this.renderNotes();
  }

  /**
   * A replay (husky1_replay, `fleetctl replay`'s renamed recording) is said beside its name
   * and above the goal tools: it looked like one more live robot, and a goal sent to it
   * reaches no robot. The tools stay (the rule cannot tell a fleet robot named x_replay).
   */
  renderReplay(name) {
    const of = replayOf(name);
    $("#robot-replay").hidden = !of;
    $("#robot-replay").textContent = of ? `replay of ${of}` : "";
    $("#replay-note").hidden = !of;
    $("#replay-note").textContent = of
      ? `${name} is a recording of ${of} played back (fleetctl replay): old data, and no robot acts on a navigation goal or initial pose sent here.`
      : "";
  }

  setSubscriptions(robot, visible) {
    const want = this.paused ? new Set() : wantedRegexes(robot, visible);
    for (const re of wantedRegexes(robot, new Set(PANELS.map((p) => p.id)))) {
      if (want.has(re)) this.conn.subscribe(re);
      else this.conn.unsubscribe(re);
    }
  }

  applyVisibility() {
    for (const p of PANELS) {
      const box = $(`#show-${p.id}`);
      if (box) box.checked = this.visible.has(p.id);
      $(`#panel-${p.id}`).hidden = !this.visible.has(p.id);
    }
    if (this.robot) this.setSubscriptions(this.robot, this.visible);
  }

  togglePanel(id, on) {
    if (on) this.visible.add(id);
    else this.visible.delete(id);
    this.applyVisibility();
  }

  togglePause() {
    this.paused = !this.paused;
    $("#pause").textContent = this.paused ? "Resume" : "Pause";
    $("#paused-note").hidden = !this.paused;
    if (this.robot) this.setSubscriptions(this.robot, this.visible);
  }

  updateCommands() {
    if (!this.robot || !this.conn) return;
    for (const [cmd, btn] of [[GOAL, "#tool-goal"], [INITIAL, "#tool-initial"]]) {
      const topic = `/${this.robot}${cmd.suffix}`;
      const ok = this.conn.rules.canSend(topic);
      $(btn).disabled = !ok;
      const replay = replayOf(this.robot) ? ` (${this.robot} is a replay: no robot acts on it)` : "";
      $(btn).title = (ok ? `Drag on the map, or type the pose, to send a ${cmd.label}` : `You may not send on ${topic}`) + replay;
    }
    const denied = [GOAL, INITIAL].filter((c) => !this.conn.rules.canSend(`/${this.robot}${c.suffix}`));
    $("#command-denied").hidden = denied.length === 0;
    $("#command-denied").textContent = denied.length
      ? `You are not allowed to send ${denied.map((c) => `a ${c.label} (${`/${this.robot}${c.suffix}`})`).join(" or ")} to ${this.robot}: your rules have no send permission for it.`
      : "";
  }

  async sendPose(kind, x, y, yaw) {
    this.tools.sent();
    const cmd = kind === "goal" ? GOAL : INITIAL;
    const topic = `/${this.robot}${cmd.suffix}`;
    if (!this.conn.rules.canSend(topic)) {
      return this.commandStatus(`Not sent: you may not send on ${topic}.`, true);
    }
    const msg = kind === "goal" ? goalMessage(x, y, yaw, this.frameId) : initialPoseMessage(x, y, yaw, this.frameId);
    try {
      const size = await this.conn.sendMessage(cmd.type, topic, msg, { noDrop: true });
      this.views.map.markSent(kind, x, y, yaw);
      this.commandStatus(`Sent ${cmd.label} x=${x.toFixed(2)} m y=${y.toFixed(2)} m yaw=${((yaw * 180) / Math.PI).toFixed(0)}° to ${topic} (${size} bytes).`);
    } catch (err) {
      this.commandStatus(`Not sent: ${err.message}`, true);
    }
  }

  /** Ask a video topic's publisher for a keyframe (the server forwards it, rate-limited). */
  async requestKeyframe(topic) {
    try {
      await this.conn.sendMessage(KEYFRAME_REQUEST.type, KEYFRAME_REQUEST.topic, { topic }, { noDrop: true });
      this.keyframeRequests.sent++;
      this.keyframeRequests.last = topic;
    } catch (err) {
      this.keyframeRequests.failed++;
      this.onServerError({ code: "keyframe_request", topic, message: String(err.message ?? err) });
    }
  }

  commandStatus(text, bad = false) {
    const el = $("#command-status");
    el.textContent = text;
    el.classList.toggle("bad", bad);
  }

  /**
   * A panel that has drawn nothing says over its canvas which topic it waits for, or what
   * arrived there instead: a robot whose camera is /cam/jpeg got a blank black panel.
   */
  waitingNote(p) {
    if (!p.draws) return "";
    const topics = p.topics.map((t) => `/${this.robot}${t}`);
    if (this.robotDenied()) return `Your sign-in may not receive ${topics.join(", ")}.`;
    if (topics.some((t) => this.seenTypes.get(t) === p.draws)) return "";
    const other = topics.find((t) => this.seenTypes.has(t));
    if (other) {
      const type = this.seenTypes.get(other);
      return type === VIDEO_TYPE
        ? `${other} arrives as video (${type}): see the Video panel.`
        : `${other} arrives as ${type}; this panel draws ${p.draws}.`;
    }
    const local = topics[0].slice(this.robot.length + 1);
    return this.paused
      ? "Paused."
      : `Nothing on ${topics.join(", ")} (${p.draws}) yet. The robot's ${local} is shown here; ` +
        `another topic needs remote_topic: ${topics[0]} in its publish entry.`;
  }

  /** The Video panel's note: nothing once video arrived, else {@link videoHint}. */
  videoNote() {
    for (const type of this.seenTypes.values()) if (type === VIDEO_TYPE) return "";
    return this.videoHint();
  }

  /** What the Video panel says while it has no stream: its topics, or what came there instead. */
  videoHint() {
    const topics = PANELS.find((p) => p.id === "video").topics.map((t) => `/${this.robot}${t}`);
    if (this.robotDenied()) return `this sign-in may not receive ${topics.join(", ")}`;
    const raw = topics.find((t) => this.seenTypes.has(t) && this.seenTypes.get(t) !== VIDEO_TYPE);
    if (raw) {
      return `${raw} arrives as ${this.seenTypes.get(raw)}, not as video: add video: {codec: h264} ` +
        "to its publish entry (fleet.yaml, or the robot's client.yaml) to see it here";
    }
    return `no video yet on ${topics.slice(0, -1).join(", ")} or ${topics[topics.length - 1]}: ` +
      "a robot sends a camera as video when its publish entry has a video: section " +
      "(fleet.yaml, or the robot's client.yaml; docs/operator.md)";
  }

  /** A panel whose topic arrives in a form the page cannot decode says so, and how to fix it. */
  renderNotes() {
    if (!this.robot || !this.conn) return;
    for (const p of PANELS) {
      const panel = $(`#panel-${p.id}`);
      const wait = panel.querySelector(".panel-wait");
      if (wait) {
        // The Video panel's hint lies over its black picture, as the other panels' notes
        // do: in the three-line status box under it, a 300 px panel cut it off mid-sentence.
        wait.textContent = p.id === "video" ? this.videoNote() : this.waitingNote(p);
        wait.hidden = !wait.textContent;
      }
      const notes = p.topics.map((t) => this.conn.unsupported.get(`/${this.robot}${t}`)).filter(Boolean);
      let note = panel.querySelector(".panel-note");
      if (!note && notes.length) {
        note = document.createElement("p");
        note.className = "panel-note bad";
        note.setAttribute("role", "status");
        // Over the top of what the panel shows (css/app.css), not in the flow: inserted
        // under the title it pushed the panel, and the map below it, down a few lines.
        panel.querySelector(".scene-row, .map-wrap, .canvas-wrap, canvas, pre, #gps-map").before(note);
      }
      if (!note) continue;
      note.textContent = notes.join(" ");
      note.hidden = notes.length === 0;
    }
  }

  /**
   * Say when what the page shows is old: the median of the topics' latencies (5 s each).
   * In the 3D scene, video, cloud and camera at once on a slow machine the page fell
   * 3.7 s behind the robots with nothing but the health table saying so.
   */
  renderBehind(rows) {
    const lat = rows.map((r) => r.latencyMs).filter(Number.isFinite).sort((a, b) => a - b);
    const behindMs = lat.length ? lat[lat.length >> 1] : 0;
    const note = $("#behind-note");
    note.hidden = !(behindMs > BEHIND_MS) || this.paused;
    note.dataset.behindMs = String(Math.round(behindMs));
    if (!note.hidden) {
      note.textContent = `${this.robot}'s data here is ${(behindMs / 1000).toFixed(1)} s old ` +
        "(the link or this browser cannot keep up, or the robot's clock is off): hide panels you do not need.";
    }
  }

  /**
   * The signed-in user's rules let nothing of the open robot through (a user scoped to
   * other robots: `fleetctl add-user --robots`, a link to another robot's page). The relay
   * lists no such robot and delivers nothing of it; the page said "not in the fleet's robot
   * list" and "Nothing on /jackal2/scan yet", which sent people looking for a broken robot.
   */
  robotDenied() {
    const rules = this.conn?.rules;
    if (!this.robot || !this.registryKnown || !rules?.readable) return false;
    const mine = (t) => rules.canReceive(`/${this.robot}${t}`);
    return !mine("/status") && !PANELS.some((p) => p.topics.some(mine));
  }

  /**
   * The open robot's state from the registry, in words beside its name: the page went on
   * looking live, with no word that the robot had gone offline.
   */
  renderRobotState() {
    const el = $("#robot-state");
    el.hidden = !this.registryKnown;
    const entry = this.registry.find((r) => r.name === this.robot);
    let state = !entry ? (this.robotDenied() ? "denied" : "unlisted") : entry.online ? "online"
      : entry.never_connected ? "never" : "offline";
    if (this.conn?.state !== "open") state = "unknown"; // the list is as old as the connection
    el.dataset.state = state;
    el.textContent = {
      unknown: "state unknown: not connected to the fleet server",
      unlisted: "not in the fleet's robot list",
      denied: "not yours: this sign-in may not receive this robot's topics",
      online: "online",
      offline: `offline, last seen ${ago(toEpochS(entry?.last_seen_s))}`,
      never: "never connected: in the fleet, not heard from yet",
    }[state];
  }

  /**
   * A panel whose topics stopped (the robot, the link or the server went quiet, or Pause)
   * is dimmed and its title says how old its data is: a robot that stopped sending left
   * every panel looking live, its odometry still saying 0.50 m/s.
   */
  renderStale(nowMs = Date.now()) {
    for (const p of PANELS) {
      const panel = $(`#panel-${p.id}`);
      const { stale, lastMs } = this.conn.health.freshness(p.topics.map((t) => `/${this.robot}${t}`), nowMs);
      // A video waiting for a keyframe shows a picture that does not move, frames arriving.
      const frozenMs = p.id === "video" ? this.views?.video.frozenMs(nowMs) ?? null : null;
      const frozen = !stale && frozenMs !== null && frozenMs > STALE_MIN_MS;
      panel.classList.toggle("stale", stale || frozen);
      let age = panel.querySelector("h3 .age");
      if (!age) {
        age = document.createElement("span");
        age.className = "age";
        panel.querySelector("h3").append(age);
      }
      age.textContent = stale ? `no data for ${duration((nowMs - lastMs) / 1000)}`
        : frozen ? `picture ${duration(frozenMs / 1000)} old, waiting for a keyframe` : "";
      age.title = age.textContent;
    }
  }

  renderHealth() {
    if (!this.conn) return;
    if (!this.robot) return this.renderOverview();
    this.renderRobotState();
    this.renderStale();
    this.renderNotes();
    this.views?.scene.renderLists();
    this.views?.video.renderStatus();
    const rows = this.conn.health.rows(`/${this.robot}/`);
    this.renderBehind(rows);
    $("#health tbody").innerHTML = rows.map((r) =>
      `<tr><td>${r.topic}</td><td>${r.rateHz.toFixed(1)}</td><td>${Number.isFinite(r.latencyMs) ? r.latencyMs.toFixed(0) : "–"}</td><td>${r.drops}</td><td>${r.received}</td></tr>`).join("");
    const s = this.conn.stats;
    $("#client-stats").textContent = `frames ${s.framesIn}, decode errors ${s.decodeErrors}, dropped while loading a type ${s.droppedNoLayout}, fragments dropped ${this.conn.reassembler.totalDropped()}, decompressed ${s.decompressed}, compressed but undecodable here ${s.unsupported}, dropped behind decompression ${s.droppedInflateQueue}`;
  }

  frame(nowMs = performance.now()) {
    if (this.robot && this.views) {
      for (const v of Object.values(this.views)) v.render?.(nowMs);
    }
    requestAnimationFrame((t) => this.frame(t));
  }
}

async function main() {
  let config;
  try {
    const resp = await fetch("config.json");
    config = await resp.json();
  } catch (err) {
    $("#signin-error").textContent = `Cannot load config.json: ${err}`;
    return;
  }
  if (!config.server_url) {
    // null: the relay serves this page itself, so its WebSocket is on the page's own origin.
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    config.server_url = `${scheme}://${location.host}/`;
    // Relay replicas (fleetctl up --replicas): the same host name on the other replicas'
    // ports, tried in turn when this one goes (docs/webviz.md, "Replicas").
    const host = location.hostname.includes(":") ? `[${location.hostname}]` : location.hostname;
    config.failover_urls = (config.replica_ports ?? [])
      .map((port) => `${scheme}://${host}:${port}/`)
      .filter((url) => url !== config.server_url);
  }
  $("#server-url").textContent = config.server_url;
  mirrorTitles(document.body);
  const app = new App(config);
  window.fleetviz = app; // for debugging from the console
  $("#signin-form").addEventListener("submit", (e) => {
    e.preventDefault();
    const token = $("#token").value.trim();
    sessionStorage.setItem("fleetctl-token", token);
    app.signIn(token);
  });
  $("#signout").addEventListener("click", () => {
    sessionStorage.removeItem("fleetctl-token");
    location.reload();
  });
  $("#pause").addEventListener("click", () => app.togglePause());
  // detail 0: a click made by the keyboard (Enter or Space on the button).
  $("#tool-goal").addEventListener("click", (e) => app.tools.arm("goal", e.detail === 0));
  $("#tool-initial").addEventListener("click", (e) => app.tools.arm("initialpose", e.detail === 0));
  document.addEventListener("keydown", (e) => {
    if (e.key === "Escape") app.tools?.cancel();
  });
  for (const p of PANELS) {
    $(`#show-${p.id}`).addEventListener("change", (e) => app.togglePanel(p.id, e.target.checked));
  }
  window.addEventListener("hashchange", () => app.conn && app.route());
  setInterval(() => app.renderHealth(), 1000);
  app.frame();
  const saved = sessionStorage.getItem("fleetctl-token");
  if (saved !== null) app.signIn(saved);
}

main();
