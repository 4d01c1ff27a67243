// Fleet overview: every robot in the server's registry (online or not), merged with live
// /<robot>/status frames and this page's link health per robot.

import { replayOf } from "../replays.js";

function esc(s) {
  return String(s ?? "").replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

/** Seconds since epoch from a registry timestamp (seconds, ms, ns or ISO text), or NaN. */
export function toEpochS(v) {
  if (v === null || v === undefined || v === "") return NaN;
  if (typeof v === "string" && Number.isNaN(Number(v))) return Date.parse(v) / 1000;
  const n = Number(v);
  if (n > 1e17) return n / 1e9;
  if (n > 1e11) return n / 1e3;
  return n;
}

/** A duration (s) as an operator reads it: "15 s", "3 min", "2 h". */
export function duration(d) {
  if (d < 120) return `${Math.round(d)} s`;
  if (d < 7200) return `${Math.round(d / 60)} min`;
  return `${Math.round(d / 3600)} h`;
}

export function ago(s, nowS = Date.now() / 1000) {
  if (!Number.isFinite(s)) return "never";
  const d = Math.max(0, nowS - s);
  return d < 2 ? "now" : `${duration(d)} ago`;
}

/**
 * One robot's row from a registry entry (the server's GET /robots record: name, online,
 * last_seen_s, status, is_ok, battery_level, location; never_connected for a robot of the
 * auth map the server has not heard from) and its latest live status frame.
 */
export function robotRow(entry, live) {
  const pick = (k) => (live && live[k] !== undefined ? live[k] : entry[k] ?? undefined);
  return {
    name: entry.name,
    online: Boolean(entry.online),
    // In the fleet's auth map, never heard from (just added, not yet installed).
    neverConnected: Boolean(entry.never_connected),
    status: pick("status") ?? "",
    isOk: pick("is_ok") ?? undefined,
    battery: pick("battery_level") ?? undefined,
    location: pick("location") ?? "",
    lastSeenS: toEpochS(entry.last_seen_s),
    replayOf: replayOf(entry.name), // a recording played back: old data, no robot acts
  };
}

/**
 * The battery column: a fraction 0..1 as the Robofleet convention has it (a robot that
 * reports 0..100 is shown as is); a negative level is the client's "unknown" (-1, sent when
 * the robot has no battery_topic), shown as a dash like a missing one, not as "-100%".
 */
export function batteryText(level) {
  if (!Number.isFinite(level) || level < 0) return "–";
  return `${Math.round(level <= 1 ? level * 100 : level)}%`;
}

/** A name as HTML that may wrap after its separators (a long one breaks there first). */
export function breakable(name) {
  return esc(name).replace(/([_./-])/g, "$1<wbr>");
}

/** The mark beside a replay's name: it looked like one more live robot. */
export function replayBadge(of) {
  if (!of) return "";
  return ` <span class="pill replay-of" title="Recorded data played back by fleetctl replay: ` +
    `no robot acts on what is sent to it">replay of ${esc(of)}</span>`;
}

export function renderOverview(tbody, rows, linkFor) {
  tbody.innerHTML = rows.map((r) => {
    const link = linkFor(r.name);
    const batt = batteryText(r.battery);
    const ok = r.isOk === undefined ? "–" : r.isOk ? "OK" : "NOT OK";
    return `<tr data-robot="${esc(r.name)}" class="${r.online ? "online" : "offline"}${r.replayOf ? " replay" : ""}">
      <td class="name"><a href="#/robot/${encodeURIComponent(r.name)}">${breakable(r.name)}</a>${replayBadge(r.replayOf)}</td>
      <td class="state nowrap">${r.online ? "online" : r.neverConnected ? "never connected" : "offline"}</td>
      <td>${esc(r.status)}</td><td class="nowrap${r.isOk === false ? " bad" : ""}">${ok}</td>
      <td class="nowrap">${batt}</td><td>${esc(r.location)}</td><td class="nowrap">${ago(r.lastSeenS)}</td>
      <td class="nowrap">${link}</td></tr>`;
  }).join("");
}
