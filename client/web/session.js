// One streaming session over the WebSocket: messages in and out, seq numbers, latency.
//
// Events (EventTarget): "welcome", "frame", "stats", "presence", "tracked", "avatar",
// "servererror", "pong", "shown", "close";
// each event's `detail` is the decoded message (close: {code, reason}; shown: {seq,
// latencyMs}, a WebRTC frame whose stamp names one of this page's drives).

import { PROTOCOL_VERSION, ProtocolError, decode, encode } from "./protocol.js";

/** The stream's URL for an avatar, or a room with `streamUrl({room})`; never with a token in
 *  it (URLs end up in logs and histories). */
export function streamUrl(target) {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const query = typeof target === "string" ? { avatar: target } : { room: target.room };
  return `${scheme}://${location.host}/v1/stream?${new URLSearchParams(query)}`;
}

/** The token from the address (#token= or ?token=), removed from the address bar and the
 *  history entry so it is neither shown, bookmarked nor sent again; null if there is none. */
export function takeToken(win) {
  const url = new URL(win.location.href);
  const fragment = new URLSearchParams(url.hash.slice(1));
  const token = fragment.get("token") || url.searchParams.get("token");
  if (fragment.has("token") || url.searchParams.has("token")) {
    fragment.delete("token");
    url.searchParams.delete("token");
    url.hash = fragment.toString();
    win.history.replaceState(win.history.state, "", url.toString());
  }
  return token || null;
}

/** Now on the page's capture clock: seconds of performance.now() (since performance.timeOrigin),
 *  the clock of every drive's and voice packet's t_capture. */
export function captureTime() {
  return performance.now() / 1000;
}

/** What both transports share: seq numbers and send times, the incoming messages as events,
 *  and the send methods. A subclass gives `_send(message, options)` and `open`. */
export class MessageSession extends EventTarget {
  constructor() {
    super();
    this.seq = 0;
    this.welcome = null;
    this.sentAt = new Map();  // seq -> performance.now() when sent
    this.bytesIn = 0;
  }

  _emit(type, detail) {
    this.dispatchEvent(new CustomEvent(type, { detail }));
  }

  _receive(data) {
    if (!(data instanceof ArrayBuffer)) return;  // the protocol is binary only
    this.bytesIn += data.byteLength;
    let message;
    try {
      message = decode(data);
    } catch (err) {
      this._emit("servererror", { code: "bad_message", message: String(err) });
      return;
    }
    if (message.type === "welcome") {
      this.welcome = message;
      this._resolve?.(message);
      this._emit("welcome", message);
    } else if (message.type === "frame") {
      message.latencyMs = this._latency(message.seq);
      this._emit("frame", message);
    } else if (message.type === "error") {
      if (!this.welcome) this._reject?.(new ProtocolError(message.code, message.message));
      this._emit("servererror", message);
    } else if (message.type === "avatar") {
      // the avatar was replaced in place (the trained demo): the welcome's now describes it
      if (this.welcome?.avatar?.id === message.avatar.id) this.welcome.avatar = message.avatar;
      this._emit("avatar", message);
    } else if (message.type === "pong") {
      message.rttMs = performance.now() - message.t;
      this._emit("pong", message);
    } else {
      this._emit(message.type, message);
    }
  }

  /** Milliseconds since drive `seq` was sent (null: not ours, or counted already; `at`: when
   *  its frame showed). Frames may skip coalesced seqs: everything up to it is forgotten. */
  _latency(seq, at = performance.now()) {
    const sent = this.sentAt.get(seq);
    for (const key of this.sentAt.keys()) if (key <= seq) this.sentAt.delete(key);
    return sent === undefined ? null : Math.max(0, at - sent);
  }

  /** A frame that shows drive `seq` was presented at `at` (WebRTC: read from its stamp). */
  shown(seq, at) {
    const latencyMs = this._latency(seq, at);
    if (latencyMs !== null) this._emit("shown", { seq, latencyMs });
  }

  _stamp() {
    this.seq += 1;
    this.sentAt.set(this.seq, performance.now());
    if (this.sentAt.size > 1000) this.sentAt.delete(this.sentAt.keys().next().value);
    return this.seq;
  }

  /** Partial parameters: {smplx: {jaw_pose: Float32Array}, ...}; returns the seq or null.
   *  Stamped with its capture time (captureTime()): frames showing it carry it back. */
  drive(families, reset = false) {
    const seq = this._stamp();
    const message = { type: "drive", seq, reset, t_capture: captureTime(), ...families };
    return this._send(message, { validate: true }) ? seq : null;
  }

  /** One Opus packet of this performer's voice (voice_ws.js), captured at `tCapture`. */
  voice(data, tCapture, levelDbov = null) {
    this.voiceSeq = (this.voiceSeq ?? -1) + 1;
    const message = { type: "voice", seq: this.voiceSeq, data, t_capture: tCapture };
    if (levelDbov !== null) message.level_dbov = levelDbov;
    return this._send(message);
  }

  view(orbit, moving = false) {
    return this._send({ type: "view", orbit, moving }, { validate: true });
  }

  request(fields) {
    return this._send({ type: "request", ...fields }, { validate: true });
  }

  /** A webcam frame to track, captured at `tCapture` (s, captureTime()'s clock): the frames
   *  of the drive tracked from it carry it, so the voice syncs to them (protocol minor 4). */
  image(bytes, format = "jpeg", tCapture = null) {
    const seq = this._stamp();
    const message = { type: "image", seq, format, data: bytes };
    if (tCapture !== null) message.t_capture = tCapture;
    return this._send(message) ? seq : null;
  }

  ping() {
    return this._send({ type: "ping", t: performance.now() });
  }
}

export class Session extends MessageSession {
  /** `token` goes in the first message, the hello, which the server reads before anything;
   *  `join` ({role, seat, voice, voiceMix}) too, in a room (voice: hear the other seats'
   *  `voice` messages; voiceMix: one mix of them instead); `name`: the display name others
   *  see. */
  constructor(url, token = null, join = {}, name = null) {
    super();
    this.url = url;
    this.ws = new WebSocket(url);
    this.ws.binaryType = "arraybuffer";
    this.ready = new Promise((resolve, reject) => {
      this._resolve = resolve;
      this._reject = reject;
    });
    this.ws.addEventListener("open", () => {
      const hello = { type: "hello", version: PROTOCOL_VERSION, client: "telesplat-web" };
      if (token) hello.token = token;
      if (join.role) hello.role = join.role;
      if (Number.isInteger(join.seat)) hello.seat = join.seat;
      if (join.voice) hello.voice = true;
      if (join.voiceMix) hello.voice_mix = true;  // watching: one mix of every seat
      if (name) hello.name = name;
      this._send(hello);
    });
    this.ws.addEventListener("message", (event) => this._receive(event.data));
    this.ws.addEventListener("close", (event) => {
      this._reject(new ProtocolError("internal", event.reason || "connection closed"));
      this._emit("close", { code: event.code, reason: event.reason });
    });
  }

  get open() {
    return this.ws.readyState === WebSocket.OPEN;
  }

  _send(message, options = {}) {
    // Nothing but the hello until welcome: before it the server reads one small message only.
    if (!this.open || (!this.welcome && message.type !== "hello")) return false;
    this.ws.send(encode(message, options));
    return true;
  }

  close() {
    this.ws.close(1000, "bye");
  }
}
