// The page meets the relay's failed-login throttle (docs/webviz.md, "Too many failed
// sign-ins"): it says so, and waits at least the relay's hint before the next attempt.
import { test } from "node:test";
import assert from "node:assert/strict";
import { Connection } from "../../../fleetctl/webviz/static/js/connection.js";
import {
  MAX_RETRY_AFTER_S, parseRetryAfter, probeUrl, retryAfterOfText, throttledClose, throttledText,
} from "../../../fleetctl/webviz/static/js/loginthrottle.js";

const REASON = "too many failed logins from this address: retry in 2 s";

class FakeSocket {
  static opened = [];
  constructor(url) {
    this.url = url;
    this.sent = [];
    FakeSocket.opened.push(this);
  }
  send(data) {
    this.sent.push(data);
  }
  close() {}
}

const loader = { layouts: new Map(), ensure: () => Promise.resolve() };

/** A Connection whose relay's probe answers `status` (Retry-After `retryAfter`), or fails (`status` null). */
function connection({ status = 204, retryAfter = null, url = "wss://host:8443/", token = "t0k" } = {}) {
  FakeSocket.opened = [];
  const probes = [];
  const fetchImpl = (url, init) => {
    probes.push({ url, headers: init.headers ?? {}, credentials: init.credentials });
    if (status === null) return Promise.reject(new TypeError("Failed to fetch")); // CORS, or down
    return Promise.resolve({ status, headers: { get: (name) => (name === "Retry-After" ? retryAfter : null) } });
  };
  const conn = new Connection({ url, token, loader, WebSocketImpl: FakeSocket, fetchImpl });
  const statuses = [];
  conn.addEventListener("status", (e) => statuses.push(e.detail));
  return { conn, probes, statuses };
}

const settle = () => new Promise((resolve) => setImmediate(resolve));

test("the relay's message, Retry-After and the 4429s that are not the throttle", () => {
  assert.equal(retryAfterOfText(REASON), 2);
  assert.equal(retryAfterOfText("identity 'x' has 64 connections open"), null);
  assert.equal(retryAfterOfText("too many failed logins from this address: retry in 86400 s"), MAX_RETRY_AFTER_S);
  assert.equal(parseRetryAfter(" 7 "), 7);
  for (const bad of [null, "", "-1", "1.5", "soon", "Wed, 21 Oct 2015 07:28:00 GMT"]) assert.equal(parseRetryAfter(bad), null);
  assert.deepEqual(throttledClose({ code: 4429, reason: REASON }, null), { retryAfterS: 2 });
  assert.deepEqual(throttledClose({ code: 4429, reason: "" }, "login_throttled"), { retryAfterS: null });
  assert.equal(throttledClose({ code: 4429, reason: "too many refused subscriptions" }, "too_many_subscriptions"), null);
  assert.equal(throttledClose({ code: 1006, reason: REASON }, null), null);
});

test("the probe goes to the relay the socket went to, whatever the page's origin", () => {
  assert.equal(probeUrl("wss://host:8443/"), "https://host:8443/login-budget");
  assert.equal(probeUrl("ws://host:8080/"), "http://host:8080/login-budget");
  assert.equal(probeUrl("wss://[fd00::1]:8444/"), "https://[fd00::1]:8444/login-budget"); // a replica
  assert.equal(probeUrl("wss://proxy.example/fleet/"), "https://proxy.example/fleet/login-budget");
});

test("an error frame and close 4429 login_throttled: said in words, and the hint is waited", () => {
  const { conn, statuses } = connection();
  conn.open();
  FakeSocket.opened[0].onopen();
  conn.onText(JSON.stringify({ type: "error", code: "login_throttled", message: REASON }));
  conn.onClose({ code: 4429, reason: REASON });
  clearTimeout(conn.retryTimer);
  assert.equal(conn.state, "throttled");
  const last = statuses.at(-1);
  assert.ok(last.retryMs >= 2000 && last.retryMs <= 2400, last.retryMs);
  assert.match(throttledText(last.retryMs), /^Too many failed sign-ins from your network address: .* Trying again in about 2\.\d s/);
  assert.ok(!throttledText(last.retryMs).includes("t0k"));
});

test("a socket refused before it opened asks the relay: a 429 is the throttle", async () => {
  const { conn, probes, statuses } = connection({ status: 429, retryAfter: "2" });
  conn.open();
  conn.onClose({ code: 1006, reason: "" }); // the browser's view of the relay's 429
  await settle();
  clearTimeout(conn.retryTimer);
  // No token and no cookies: a simple cross-origin GET, no preflight.
  assert.deepEqual(probes, [{ url: "https://host:8443/login-budget", headers: {}, credentials: "omit" }]);
  assert.equal(conn.state, "throttled");
  assert.ok(statuses.at(-1).retryMs >= 2000);
  // The next socket opens: the throttle is over.
  conn.open();
  FakeSocket.opened.at(-1).onopen();
  assert.equal(conn.throttle, null);
  assert.deepEqual(JSON.parse(FakeSocket.opened.at(-1).sent[0]), { token: "t0k" });
});

test("a 429 without a usable Retry-After: throttled, at the normal backoff", async () => {
  const { conn, statuses } = connection({ status: 429, retryAfter: "later" });
  conn.open();
  conn.onClose({ code: 1006, reason: "" });
  await settle();
  clearTimeout(conn.retryTimer);
  assert.equal(conn.state, "throttled");
  assert.ok(statuses.at(-1).retryMs < 1000); // 250 ms x jitter
});

test("a refused socket whose relay answers otherwise, or not at all, is a plain disconnect", async () => {
  // 204: within the budget; 404: a relay without the probe; null: down, or no CORS.
  for (const status of [204, 404, null]) {
    const { conn, probes } = connection({ status });
    conn.open();
    conn.onClose({ code: 1006, reason: "" });
    await settle();
    clearTimeout(conn.retryTimer);
    assert.equal(conn.state, "disconnected", String(status));
    assert.equal(probes.length, 1);
  }
});

test("a page without a token asks too (the relay refuses its upgrade all the same)", async () => {
  const { conn, probes } = connection({ status: 429, retryAfter: "2", token: null });
  conn.open();
  conn.onClose({ code: 1006, reason: "" });
  await settle();
  clearTimeout(conn.retryTimer);
  assert.equal(conn.state, "throttled");
  assert.equal(probes.length, 1);
});

test("stopped while asking: no attempt is scheduled", async () => {
  const { conn } = connection({ status: 429, retryAfter: "2" });
  conn.open();
  conn.onClose({ code: 1006, reason: "" });
  conn.stop();
  await settle();
  assert.equal(conn.retryTimer, null);
  assert.equal(FakeSocket.opened.length, 1);
});
