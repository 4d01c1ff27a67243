// Connection's replica failover (issue 15): after a close, the next attempt goes to the
// next URL of [url, ...failoverUrls]; the backoff doubles only after a whole round.
import { test } from "node:test";
import assert from "node:assert/strict";
import { Connection } from "../../../fleetctl/webviz/static/js/connection.js";

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
  return new Connection({ url: "wss://host:8443/", failoverUrls, token: "t", loader, WebSocketImpl: FakeSocket });
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
