// The map's pose form: x, y (m) and yaw (degrees) for the armed tool, shown under the map
// (under it, not above: nothing moves the map between a tool's button and a press on it).
// Enter sends, Esc or Cancel cancels (app.js); reading and checking are poseform.js's.

import { formatPose, parsePose } from "../poseform.js";

const FIELDS = ["x", "y", "yaw"];

export class PoseEntry {
  /**
   * @param {{form: HTMLFormElement, x: HTMLInputElement, y: HTMLInputElement,
   *          yaw: HTMLInputElement, frame: HTMLElement, error: HTMLElement,
   *          cancel: HTMLButtonElement}} els
   * @param {{onSubmit: (pose: {x: number, y: number, yaw: number}) => void,
   *          onCancel: () => void, onChange: (pose: object|null, typed: boolean) => void}} handlers
   *   onChange: the pose in the fields (null while one does not read), for the preview;
   *   typed: it came from the keyboard, not from a drag (setPose)
   */
  constructor(els, { onSubmit, onCancel, onChange }) {
    this.els = els;
    this.onChange = onChange;
    els.form.addEventListener("submit", (e) => {
      e.preventDefault(); // Enter in a field, or the Send button
      const pose = this.read();
      if (pose) onSubmit(pose);
    });
    els.cancel.addEventListener("click", () => onCancel());
    for (const name of FIELDS) {
      els[name].addEventListener("input", () => {
        this.clearError();
        this.onChange(this.parse().pose ?? null, true);
      });
    }
  }

  get open() {
    return !this.els.form.hidden;
  }

  /** Show the form for a tool (*label* says which) with *pose* in it, in *frameId*. */
  show(label, pose, frameId) {
    this.els.form.dataset.tool = label;
    this.els.form.setAttribute("aria-label", `${label}: type x, y and yaw, Enter sends`);
    this.els.frame.textContent = `frame ${frameId}`;
    this.clearError();
    this.els.form.hidden = false;
    this.setPose(pose);
  }

  hide() {
    this.els.form.hidden = true;
    this.clearError();
  }

  /** Put *pose* in the fields (a drag, a key on the map, the start). */
  setPose(pose) {
    const texts = formatPose(pose);
    for (const name of FIELDS) this.els[name].value = texts[name];
    this.clearError();
    this.onChange(this.parse().pose ?? null, false);
  }

  /** Whether focus is in the form (it is about to be hidden: focus must go somewhere). */
  hasFocus() {
    return this.els.form.contains(document.activeElement);
  }

  parse() {
    return parsePose(Object.fromEntries(FIELDS.map((n) => [n, this.els[n].value])));
  }

  /** The pose typed, or null: the first bad field then says why and has the focus. */
  read() {
    const got = this.parse();
    if (got.pose) return got.pose;
    const field = this.els[got.field];
    field.setAttribute("aria-invalid", "true");
    this.els.error.textContent = `Not sent: ${got.error}.`;
    this.els.error.hidden = false;
    field.focus();
    field.select();
    return null;
  }

  clearError() {
    for (const name of FIELDS) this.els[name].removeAttribute("aria-invalid");
    this.els.error.hidden = true;
    this.els.error.textContent = "";
  }

  /** Focus the first field, its text selected (typing replaces it). */
  focus(preventScroll = false) {
    this.els.x.focus({ preventScroll });
    this.els.x.select();
  }
}
