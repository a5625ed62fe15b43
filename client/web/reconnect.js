// Reconnecting after a server restart: when to try again, and how long to wait.
//
// The server tells every participant error `restarting` and closes with 1012 on SIGTERM; after
// a crash or `kill -9` connections just drop (1006). Rooms and invitations are stored, so the
// page joins the same room, with the same token, role and seat. The waits: 0.25 s doubling to
// 4 s, each shortened by a random part of up to half (so pages that lost one server do not
// all come back at once), at most `attempts` tries in a row (`?reconnect=N` in the address;
// 0: never). A room that is gone or a token no longer valid stops it at once.

export const RECONNECT = Object.freeze({ attempts: 12, initialMs: 250, maxMs: 4000, jitter: 0.5 });
export const RETRY_CLOSE_CODES = Object.freeze([1001, 1006, 1012]);  // going away, dropped, restart
// Close codes and error codes after which waiting does not help.
const FINAL_CLOSE_CODES = { 4401: "unauthorized", 4403: "forbidden", 4404: "not_found", 4410: "gone" };
const FINAL_ERROR_CODES = ["unauthorized", "forbidden", "not_found", "gone", "version"];

/** The policy of an address's `?reconnect=N` (tries; 0 turns reconnecting off). */
export function reconnectPolicy(search) {
  const asked = new URLSearchParams(search).get("reconnect");
  const attempts = asked === null ? NaN : Number.parseInt(asked, 10);
  return Number.isInteger(attempts) && attempts >= 0 && attempts <= 1000
    ? { ...RECONNECT, attempts } : { ...RECONNECT };
}

/** Milliseconds to wait before try `attempt` (0-based); `random()` in [0, 1). */
export function backoffDelay(attempt, policy = RECONNECT, random = Math.random) {
  const base = Math.min(policy.maxMs, policy.initialMs * 2 ** Math.min(attempt, 32));
  return base * (1 - policy.jitter * random());
}

/** What to do once a session ended: "retry", "stop" (the room is gone, the token refused) or
 *  null (an ordinary end: nothing to do). `closeCode`: the WebSocket's (WHEP: 1006 when the
 *  peer dropped); `errorCode`: the last `error` the server sent, if any; `failure`: an error
 *  thrown while connecting (a ProtocolError with `.code`, or fetch's TypeError: no server). */
export function reconnectDecision({ closeCode = null, errorCode = null, failure = null } = {}) {
  if (failure) {
    if (FINAL_ERROR_CODES.includes(failure.code)) return "stop";
    return "retry";  // no server yet, refused while it starts, busy, internal
  }
  if (errorCode === "restarting") return "retry";
  if (FINAL_ERROR_CODES.includes(errorCode) || closeCode in FINAL_CLOSE_CODES) return "stop";
  return RETRY_CLOSE_CODES.includes(closeCode) ? "retry" : null;
}

/** The words for a stop: why this page will not reconnect. */
export function stopReason({ closeCode = null, errorCode = null, failure = null } = {}) {
  const code = failure?.code ?? errorCode ?? FINAL_CLOSE_CODES[closeCode];
  if (code === "not_found" || code === "gone") return "the room is gone (deleted or closed)";
  if (code === "unauthorized") return "the link's token is no longer valid";
  if (code === "forbidden") return "the seat is taken or the token may not join this way";
  return `the server refused (${code})`;
}
