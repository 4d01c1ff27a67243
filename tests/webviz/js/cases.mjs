// Shared loader for the fixture directory written by tests/webviz/test_js_unit.py.
import { readFileSync, existsSync } from "node:fs";
import { join } from "node:path";
import { Layouts } from "../../../fleetctl/webviz/static/js/fb/layout.js";

export const DIR = process.env.FLEETCTL_WEBVIZ_CASES;
export const HAVE = DIR !== undefined && existsSync(join(DIR, "cases.json"));
export const cases = HAVE ? JSON.parse(readFileSync(join(DIR, "cases.json"), "utf8")) : null;

export function frame(name) {
  const b = readFileSync(join(DIR, "frames", name));
  // A fresh, 8-aligned ArrayBuffer, as a WebSocket hands frames to the page.
  const out = new Uint8Array(b.length);
  out.set(b);
  return out;
}

export function layoutsFor(...types) {
  const l = new Layouts();
  for (const t of types) l.add(JSON.parse(readFileSync(join(DIR, "types", `${t}.json`), "utf8")));
  return l;
}

/** Compare a decoded value with the Python codec's canonical JSON; returns a path or null. */
export function mismatch(actual, expected, path = "") {
  if (typeof expected === "string") {
    return String(actual) === expected ? null : `${path}: ${String(actual)} != ${expected}`;
  }
  if (typeof expected === "number" || typeof expected === "boolean") {
    return actual === expected ? null : `${path}: ${actual} != ${expected}`;
  }
  if (Array.isArray(expected)) {
    if (actual == null || actual.length !== expected.length) return `${path}: length ${actual?.length} != ${expected.length}`;
    for (let i = 0; i < expected.length; i++) {
      const m = mismatch(actual[i], expected[i], `${path}[${i}]`);
      if (m) return m;
    }
    return null;
  }
  for (const k of Object.keys(expected)) {
    if (actual == null || !(k in actual)) return `${path}.${k}: missing`;
    const m = mismatch(actual[k], expected[k], `${path}.${k}`);
    if (m) return m;
  }
  return null;
}
