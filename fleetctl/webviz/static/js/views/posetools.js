// The map's two command tools, navigation goal and initial pose (docs/webviz.md,
// "Commands"): arming one (its button, the form under the map, the keys on the focused
// map), cancelling, and what the line under the map says while aiming. Sending is the
// page's one sendPose, whichever way the pose was given: a drag, the form or the keys.

import { GOAL, INITIAL } from "../commands.js";
import { initialPose, keyedPose } from "../poseform.js";
import { PoseEntry } from "./poseentry.js";

/** "Navigation goal" / "Initial pose" for a map tool. */
export function toolLabel(kind) {
  const label = kind === "goal" ? GOAL.label : INITIAL.label;
  return `${label[0].toUpperCase()}${label.slice(1)}`;
}

export class PoseTools {
  /**
   * @param {{map: import("./map.js").MapView, form: object,
   *          buttons: {goal: HTMLButtonElement, initialpose: HTMLButtonElement},
   *          say: (text: string) => void, send: (kind: string, x: number, y: number, yaw: number) => void,
   *          frameId: () => string}} opts
   *   form: the elements of PoseEntry; say: the line under the map; send: the page's
   *   sendPose; frameId: the frame a pose is sent in (the robot's latest pose message's)
   */
  constructor({ map, form, buttons, say, send, frameId }) {
    this.map = map;
    this.buttons = buttons;
    this.say = say;
    this.send = send;
    this.frameId = frameId;
    this.entry = new PoseEntry(form, {
      onSubmit: (pose) => this.submit(pose),
      onCancel: () => this.cancel(),
      onChange: (pose, typed) => this.map.setPreview(pose, typed),
    });
  }

  /**
   * A tool's button: the map waits for a press and drag, and the form under it for a typed
   * pose, focused (the button again, Esc or Cancel cancels). Without a mouse, or for an
   * exact pose (a dock at x=12.5, y=-3.0, yaw 180°), a drag was no way.
   * @param {boolean} byKeyboard the button was pressed from the keyboard
   */
  arm(kind, byKeyboard = false) {
    const map = this.map;
    if (map.tool === kind) return this.cancel();
    map.cancelDrag();
    map.setTool(kind);
    const lastSent = map.sent.find((p) => p.kind === kind);
    this.entry.show(toolLabel(kind), initialPose(lastSent, map.pose, map.center), this.frameId());
    // A pointer on its way to the map: focus without scrolling the form into view, which
    // would move the map under it.
    this.entry.focus(!byKeyboard);
    // Four lines in a 300 px panel: the box under the map keeps four (css/app.css).
    this.say(`${toolLabel(kind)}: press on the map and drag toward the heading; or type x, y ` +
      "and yaw, Enter sends; or arrow keys and Q/E on the focused map. Esc cancels.");
    this.showArmed();
  }

  /** Disarm the map's tool, a press in progress included (nothing is sent). */
  cancel() {
    const kind = this.map.tool;
    if (!kind) return;
    this.disarm();
    this.say(`${toolLabel(kind)}: cancelled.`);
  }

  /** Drop the tool and its form; focus that was in the form goes to the tool's button. */
  disarm() {
    const kind = this.map.tool;
    const refocus = this.entry.hasFocus();
    this.map.cancelDrag();
    this.map.setTool(null);
    this.entry.hide();
    this.showArmed();
    if (refocus && kind) this.buttons[kind].focus();
  }

  /** The form's pose (Enter, Send, or Enter on the map): sent as a drag to it would be. */
  submit(pose) {
    const kind = this.map.tool;
    if (!kind) return;
    this.disarm();
    this.send(kind, pose.x, pose.y, pose.yaw);
  }

  /**
   * A key on the focused map with a tool armed: arrows move the pose, Q/E turn it (the
   * form follows), Enter sends it. Returns whether the key was used.
   */
  onKey(e) {
    if (e.ctrlKey || e.altKey || e.metaKey) return false;
    if (e.key === "Enter") {
      const pose = this.entry.read();
      if (pose) this.submit(pose);
      return true;
    }
    const from = this.entry.parse().pose ?? this.map.preview;
    const next = from && keyedPose(from, e.key, e.shiftKey);
    if (!next) return false;
    this.entry.setPose(next);
    this.map.setPreview(next, true);
    this.aimStatus(this.map.tool, next.x, next.y, next.yaw, "Enter to send");
    return true;
  }

  /** The pointer over the map with a tool armed; while dragging, the form follows. */
  onAim(kind, x, y, yaw) {
    if (yaw !== null) this.entry.setPose({ x, y, yaw });
    this.aimStatus(kind, x, y, yaw);
  }

  /**
   * Where an armed tool points, in metres and degrees, as the pointer moves: the pose sent
   * was said only after the release, so a goal could not be placed to a number.
   */
  aimStatus(kind, x, y, yaw, send = "release to send") {
    const where = `${toolLabel(kind)} at x=${x.toFixed(2)} m y=${y.toFixed(2)} m`;
    this.say(yaw === null
      ? `${where} (${this.frameId()}): press here, drag toward the heading and release (Esc cancels).`
      : `${where}, yaw=${((yaw * 180) / Math.PI).toFixed(0)}° (${this.frameId()}): ${send} (Esc cancels).`);
  }

  /** A pose is being sent (a drag sends without the form): nothing is armed any more. */
  sent() {
    this.entry.hide();
    this.showArmed();
  }

  showArmed() {
    for (const [kind, button] of Object.entries(this.buttons)) button.classList.toggle("active", this.map.tool === kind);
  }
}
