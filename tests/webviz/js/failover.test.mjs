// Connection's replica failover (issue 15): after a close, the next attempt goes to the
// next URL of [url, ...failoverUrls]; the backoff doubles only after a whole round.
import { test } from "node:test";
import assert from "node:assert/strict";
import { Connection, layoutsOf } from "../../../fleetctl/webviz/static/js/connection.js";
import { LayoutLoader } from "../../../fleetctl/webviz/static/js/fb/layout.js";

class FakeSocket {
  static opened = [];
  constructor(url) {
    this.url = url;
    FakeSocket.opened.push(this);
  }
  send() {}
  close() {}
}

const loader = { layouts: new Map(), ensure: () => Promise.resolve() };

function connection(failoverUrls) {
  FakeSocket.opened = [];
  // fetchImpl null: no login-budget question (loginthrottle.test.mjs), so no real request
  // to "host", and each close is decided at once.
  return new Connection({ url: "wss://host:8443/", failoverUrls, token: "t", loader, WebSocketImpl: FakeSocket, fetchImpl: null });
}

function closeAndRetry(conn, code = 1006) {
  clearTimeout(conn.retryTimer); // the test opens the next attempt itself, not a timer
  conn.onClose({ code, reason: "" });
  clearTimeout(conn.retryTimer);
  conn.open();
}

test("after a close the next replica is tried, in turn, and the list wraps", () => {
  const conn = connection(["wss://host:8444/", "wss://host:8443/", "wss://host:8445/"]);
  assert.deepEqual(conn.urls, ["wss://host:8443/", "wss://host:8444/", "wss://host:8445/"]);
  conn.open();
  for (let i = 0; i < 4; i++) closeAndRetry(conn);
  assert.deepEqual(FakeSocket.opened.map((s) => s.url), [
    "wss://host:8443/", "wss://host:8444/", "wss://host:8445/", "wss://host:8443/", "wss://host:8444/",
  ]);
});

test("the backoff doubles once per round of the list, and a welcome keeps the replica", () => {
  const conn = connection(["wss://host:8444/"]);
  conn.open();
  const start = conn.backoffMs;
  closeAndRetry(conn); // -> 8444, same round
  assert.equal(conn.backoffMs, start);
  closeAndRetry(conn); // -> 8443, a new round
  assert.equal(conn.backoffMs, start * 2);
  closeAndRetry(conn); // -> 8444
  conn.onText(JSON.stringify({ type: "welcome", rules: [], identities: [] }));
  assert.equal(conn.url, "wss://host:8444/");
  assert.equal(conn.backoffMs, start); // reset by the welcome
});

test("a refusal is not retried anywhere (the token is wrong on every replica)", () => {
  const conn = connection(["wss://host:8444/"]);
  conn.open();
  clearTimeout(conn.retryTimer);
  conn.onClose({ code: 4401, reason: "" });
  assert.equal(conn.state, "refused");
  assert.equal(conn.retryTimer, null);
  assert.equal(FakeSocket.opened.length, 1);
});

test("without replicas the one URL is retried as before", () => {
  const conn = connection([]);
  conn.open();
  closeAndRetry(conn);
  closeAndRetry(conn);
  assert.deepEqual(FakeSocket.opened.map((s) => s.url), ["wss://host:8443/", "wss://host:8443/", "wss://host:8443/"]);
});

test("layouts come from the replica the page is connected to", () => {
  assert.equal(layoutsOf("wss://fleet.example:8444/"), "https://fleet.example:8444/types/");
  assert.equal(layoutsOf("ws://[::1]:8080/"), "http://[::1]:8080/types/");
});

test("a layout fetch nobody answered is asked again; a 404 is remembered", async () => {
  let base = "https://a:8443/types/";
  const asked = [];
  const layout = { root: "Empty", metadata: "Meta",
    tables: { Empty: { fields: [] }, Meta: { fields: [] } } };
  const fetchFn = async (url) => {
    asked.push(url);
    if (url.startsWith("https://a:")) throw new TypeError("Failed to fetch");
    if (url.includes("Missing")) return { ok: false, status: 404, text: async () => "no" };
    return { ok: true, json: async () => layout };
  };
  const loader = new LayoutLoader(() => base, fetchFn);
  await assert.rejects(loader.ensure("std_msgs/msg/Empty"));
  base = "https://b:8444/types/"; // failed over to replica B
  await loader.ensure("std_msgs/msg/Empty");
  assert.deepEqual(asked, ["https://a:8443/types/std_msgs/msg/Empty.json",
    "https://b:8444/types/std_msgs/msg/Empty.json"]);
  await assert.rejects(loader.ensure("std_msgs/msg/Missing"));
  await assert.rejects(loader.ensure("std_msgs/msg/Missing"));
  assert.equal(asked.filter((u) => u.includes("Missing")).length, 1);
});
