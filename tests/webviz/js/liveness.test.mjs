// Connection's watchdog: a socket that does not answer (a hung relay, a dead path TCP does
// not report) is given up after SILENT_MS and reconnected, instead of staying "open".
import { test } from "node:test";
import assert from "node:assert/strict";
import { Connection, SILENT_MS } from "../../../fleetctl/webviz/static/js/connection.js";

class FakeSocket {
  static opened = [];
  constructor(url) {
    this.url = url;
    this.sent = [];
    this.closed = null;
    FakeSocket.opened.push(this);
  }
  send(data) {
    this.sent.push(data);
  }
  close(code, reason) {
    this.closed = { code, reason };
  }
}

const loader = { layouts: new Map(), ensure: () => Promise.resolve() };
const WELCOME = JSON.stringify({ type: "welcome", rules: [], identities: [] });

function connection() {
  FakeSocket.opened = [];
  const probes = [];
  const fetchImpl = (url) => {
    probes.push(url);
    return new Promise(() => {}); // a hung relay never answers
  };
  const conn = new Connection({ url: "wss://host:8443/", token: "t", loader, WebSocketImpl: FakeSocket, fetchImpl });
  const statuses = [];
  conn.addEventListener("status", (e) => statuses.push(e.detail));
  return { conn, probes, statuses };
}

test("an open socket whose server stops answering is given up and retried", () => {
  const { conn, probes, statuses } = connection();
  conn.open();
  const ws = FakeSocket.opened[0];
  ws.onopen();
  ws.onmessage({ data: WELCOME });
  assert.equal(conn.state, "open");
  assert.equal(conn.waitingSinceMs, null); // nothing asked, nothing to wait for
  assert.equal(conn.checkSilence(Date.now() + 10 * SILENT_MS), false);

  conn.listRobots(); // answered: still open, however long after
  const asked = conn.waitingSinceMs;
  assert.ok(asked !== null);
  ws.onmessage({ data: JSON.stringify({ type: "robots", robots: [] }) });
  assert.equal(conn.checkSilence(asked + 10 * SILENT_MS), false);

  conn.listRobots(); // unanswered: the first ask counts, not the later ones
  const first = conn.waitingSinceMs;
  conn.listRobots();
  assert.equal(conn.waitingSinceMs, first);
  assert.equal(conn.checkSilence(first + SILENT_MS), false);
  assert.equal(conn.checkSilence(first + SILENT_MS + 1000), true);
  clearTimeout(conn.retryTimer);
  assert.deepEqual(ws.closed, { code: 4000, reason: "no answer" });
  assert.equal(ws.onmessage, null); // a late frame or close of the dead socket is ignored
  assert.equal(conn.ws, null);
  assert.equal(conn.state, "disconnected");
  assert.equal(statuses.at(-1).detail, `no answer from the server for ${Math.round(SILENT_MS / 1000) + 1} s`);
  assert.deepEqual(probes, []); // no throttle question: a 429 is answered at once
});

test("a socket that never opens, or opens and never welcomes, is given up too", () => {
  const { conn, statuses } = connection();
  conn.open();
  const start = conn.waitingSinceMs;
  assert.equal(conn.checkSilence(start + SILENT_MS + 1), true); // the upgrade hung
  clearTimeout(conn.retryTimer);
  assert.equal(statuses.at(-1).state, "disconnected");
  conn.open();
  FakeSocket.opened[1].onopen(); // opened, the token sent, no welcome
  assert.equal(conn.checkSilence(conn.waitingSinceMs + SILENT_MS + 1), true);
  clearTimeout(conn.retryTimer);
  assert.equal(FakeSocket.opened[1].closed.code, 4000);
});

test("binary frames count as answers; a stopped connection is not watched", () => {
  const { conn } = connection();
  conn.open();
  const ws = FakeSocket.opened[0];
  ws.onopen();
  ws.onmessage({ data: WELCOME });
  conn.listRobots();
  ws.onmessage({ data: new ArrayBuffer(4) }); // undecodable, but the server is there
  assert.equal(conn.waitingSinceMs, null);
  conn.listRobots();
  conn.stop();
  assert.equal(conn.checkSilence(Date.now() + 10 * SILENT_MS), false);
  assert.equal(FakeSocket.opened[0].closed.code, 1000); // closed by stop(), not given up
});
