// The relay's failed-login throttle, as the page can see it (docs/webviz.md, "Too many
// failed sign-ins"; the relay's side: docs/security.md, "Failed logins").
//
// Past an address's failed-login budget (an IPv4 address or IPv6 /64: 20 failures, then
// one per 2 s) the relay refuses every token from it unhashed:
// - a token frame gets an error frame {code: "login_throttled"} and close 4429, reason
//   "too many failed logins from this address: retry in N s";
// - an upgrade that could only sign in by a token frame (the page's) gets HTTP 429 with
//   Retry-After. The WebSocket API hides an upgrade's status: the page sees a close 1006
//   before the socket opened, as for a server that is down. So after such a close the page
//   asks the relay the socket went to, whatever origin the page came from (a replica, a
//   relay behind `fleetctl webviz`): GET /login-budget, without a token or cookies (a
//   simple cross-origin request, no preflight; the relay answers any origin), 204 within
//   the budget, 429 with Retry-After over it. Asking costs the relay no hash and no failure.
//   A relay without the probe, or none at all, gives no readable answer: a plain disconnect.
// 4429 alone is not enough: the relay also closes with 4429 for too many connections of
// one identity and for a subscription flood; the reason or the error frame says which.

export const THROTTLED_CLOSE = 4429;
export const THROTTLED_ERROR = "login_throttled";
// Our relay never asks for more than 2 s; a proxy's limiter may say an hour, but a page
// that stops trying for that long looks dead (the user reloads it). Same cap as the robot
// client (fleetctl.client.loginthrottle.MAX_RETRY_AFTER_S).
export const MAX_RETRY_AFTER_S = 300;
const MESSAGE = /too many failed logins from this address: retry in ([0-9]{1,9}) s/;

/** Seconds in the relay's "... retry in N s" message (capped), or null when not that message. */
export function retryAfterOfText(text) {
  const m = MESSAGE.exec(text ?? "");
  return m ? Math.min(Number(m[1]), MAX_RETRY_AFTER_S) : null;
}

/** A Retry-After header's seconds (delay-seconds only; capped), or null: missing or unreadable. */
export function parseRetryAfter(value) {
  const text = (value ?? "").trim();
  return /^[0-9]{1,9}$/.test(text) ? Math.min(Number(text), MAX_RETRY_AFTER_S) : null;
}

/**
 * The throttle a close reports, or null.
 * @param {{code: number, reason: string}} ev the close event
 * @param {string|null} lastErrorCode the code of the last error frame on that socket
 * @returns {{retryAfterS: number|null}|null} retryAfterS null: no usable hint
 */
export function throttledClose(ev, lastErrorCode) {
  if (ev.code !== THROTTLED_CLOSE) return null;
  const retryAfterS = retryAfterOfText(ev.reason);
  if (retryAfterS === null && lastErrorCode !== THROTTLED_ERROR) return null;
  return { retryAfterS };
}

const PROBE_TIMEOUT_MS = 5000;

/**
 * The http(s) URL of the relay's login-budget probe beside a ws(s) URL (relative: a relay
 * behind a reverse proxy's path prefix is asked under that prefix).
 */
export function probeUrl(wsUrl) {
  const url = new URL("login-budget", wsUrl);
  url.protocol = url.protocol === "wss:" ? "https:" : "http:";
  return url.href;
}

/**
 * After a socket closed before it opened: was it the relay's 429 (too many failed logins)?
 * @param {string} wsUrl the URL the socket went to
 * @param {typeof fetch|undefined} fetchImpl
 * @returns {Promise<{retryAfterS: number|null}|false|null>|null} null at once: cannot ask
 *   (no fetch); else the answer: throttled with the relay's hint, false: not throttled,
 *   null: no readable answer (a plain disconnect)
 */
export function probeThrottle(wsUrl, fetchImpl) {
  if (!fetchImpl) return null;
  // Bounded: the next attempt waits for this answer, and a relay that hangs would never give it.
  const signal = globalThis.AbortSignal?.timeout?.(PROBE_TIMEOUT_MS);
  // No token, no cookies: nothing of the page's leaves for an origin it may not trust.
  return fetchImpl(probeUrl(wsUrl), { credentials: "omit", cache: "no-store", signal }).then(
    (resp) => (resp.status === 429 ? { retryAfterS: parseRetryAfter(resp.headers.get("Retry-After")) } : false),
    () => null,
  );
}

/** What the banner says while throttled (the token is never in it). */
export function throttledText(retryMs) {
  return (
    "Too many failed sign-ins from your network address: the fleet server refuses every " +
    "token from it for now (a wrong token in this or another browser, a script or a robot " +
    "behind the same address or NAT; check them). " +
    `Trying again in about ${(retryMs / 1000).toFixed(1)} s …`
  );
}
