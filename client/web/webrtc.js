// The page's WebRTC transport: WHEP into a room (POST the SDP offer, get the answer and the
// session's resource URL; DELETE it to leave), the avatar as a video track shown in a <video>,
// and the WebSocket's msgpack messages (drive, view, request, ping, image) on a data channel
// labelled "telesplat". WhepSession has Session's interface (session.js): `ready` resolves to
// the welcome, the same send methods, the same events, so app.js drives either transport.

import { LipSync } from "./lipsync.js";
import { ProtocolError, encode } from "./protocol.js";
import { rtcSample, rtcSummary, watchStamps } from "./rtcstats.js";
import { MessageSession } from "./session.js";

const GATHER_TIMEOUT_MS = 5000;    // non-trickle: the offer waits for its candidates, bounded
const WELCOME_TIMEOUT_MS = 20000;  // answer -> ICE -> DTLS -> channel open -> welcome
export const CHANNEL_LABEL = "telesplat";

// The server's HTTP refusals as the protocol's error codes, so the page words them alike.
const HTTP_CODES = {
  400: "invalid", 401: "unauthorized", 403: "forbidden", 404: "not_found", 413: "too_large",
  415: "unsupported", 429: "rate_limited", 503: "busy",
};

/** "webrtc" or "ws", and why: `?transport=ws|webrtc` wins, else WebRTC when this browser has
 *  RTCPeerConnection and the server's /v1/health says `webrtc: true`. */
export function chooseTransport(asked, browserHasRtc, health) {
  if (asked === "ws") return { transport: "ws", why: "asked for (?transport=ws)" };
  if (!browserHasRtc) return { transport: "ws", why: "this browser has no RTCPeerConnection" };
  if (!health?.webrtc) return { transport: "ws", why: "the server offers no WebRTC" };
  return { transport: "webrtc", why: asked === "webrtc" ? "asked for" : "supported by both ends" };
}

/** Whether the WebSocket may succeed where WebRTC failed: yes for WebRTC's own limits (429,
 *  503), codecs, ICE or DTLS failures and timeouts; no for the token or the room (401, 403,
 *  404), which the WebSocket would refuse alike. `err`: a ProtocolError or an api() error. */
export function worthFallingBack(err) {
  const code = err?.code ?? { 401: "unauthorized", 403: "forbidden", 404: "not_found" }[err?.status];
  return !["unauthorized", "forbidden", "not_found"].includes(code);
}

/** DELETE a room (the solo page's private one); `keepalive` so it still goes while the page
 *  unloads. Errors are ignored: the server closes an idle room anyway. */
export function deleteRoom(roomId, token, keepalive = false) {
  fetch(`/v1/rooms/${encodeURIComponent(roomId)}`, {
    method: "DELETE", keepalive, headers: token ? { Authorization: `Bearer ${token}` } : {},
  }).catch(() => { /* closed for idleness later */ });
}

/** GET /v1/health (no token needed), or null when the server does not answer it. */
export async function serverHealth() {
  try {
    const response = await fetch("/v1/health");
    return response.ok ? await response.json() : null;
  } catch {
    return null;
  }
}

/** `callback()` for each frame the <video> presents (no-op where the browser lacks
 *  requestVideoFrameCallback: the overlay's decoded count still shows progress). */
export function onVideoFrame(video, callback) {
  if (!video.requestVideoFrameCallback) return;
  const tick = () => {
    callback();
    video.requestVideoFrameCallback(tick);
  };
  video.requestVideoFrameCallback(tick);
}

/** The WHEP URL of a room with the stream's query (size, rate, seat...), empty values left out. */
export function whepUrl(roomId, query = {}) {
  const search = new URLSearchParams();
  for (const [key, value] of Object.entries(query)) {
    if (value !== undefined && value !== null && value !== "") search.set(key, String(value));
  }
  const tail = search.toString();
  return `/v1/rooms/${encodeURIComponent(roomId)}/whep${tail ? `?${tail}` : ""}`;
}

function gathered(pc, timeoutMs) {
  if (pc.iceGatheringState === "complete") return Promise.resolve();
  return new Promise((resolve) => {
    const done = () => {
      clearTimeout(timer);
      pc.removeEventListener("icegatheringstatechange", check);
      resolve();
    };
    const check = () => { if (pc.iceGatheringState === "complete") done(); };
    // Past the deadline the offer goes with the candidates it has (host ones come first).
    const timer = setTimeout(done, timeoutMs);
    pc.addEventListener("icegatheringstatechange", check);
  });
}

async function httpError(response) {
  let detail = response.statusText;
  try {
    const body = await response.json();
    detail = body.detail ?? body.message ?? detail;
  } catch { /* not JSON */ }
  const text = typeof detail === "string" ? detail : JSON.stringify(detail);
  return new ProtocolError(HTTP_CODES[response.status] ?? "internal", `${response.status} ${text}`);
}

export class WhepSession extends MessageSession {
  /** `video`: the <video> the track plays in; `query`: WHEP query (width, height, fps, seat,
   *  name); `stamps`: frames carry their drive seq (stamp=1), read back for the latency;
   *  `media(pc)`: adds more m-lines before the offer (voice.js: microphone, seats' voices);
   *  `lipSync`: hold the picture while a voice plays, which the browser plays late
   *  (lipsync.js). */
  constructor(roomId, token, { video, query = {}, iceServers = [], stamps = false,
    media = null, lipSync = true } = {}) {
    super();
    this.transport = "webrtc";
    this.url = whepUrl(roomId, stamps ? { ...query, stamp: 1 } : query);
    this._unwatch = stamps && video ? watchStamps(video, (seq, at) => this.shown(seq, at)) : null;
    this.token = token;
    this.resource = null;     // the WHEP session's URL (Location), DELETEd on close
    this.closed = false;
    this.rtc = null;          // the newest rtcSummary()
    this._sample = null;
    this.pc = new RTCPeerConnection({ iceServers });
    this.pc.addTransceiver("video", { direction: "recvonly" });
    this.lipSync = lipSync ? new LipSync(this.pc) : null;
    media?.(this.pc);
    this.channel = this.pc.createDataChannel(CHANNEL_LABEL, { ordered: true });
    this.channel.binaryType = "arraybuffer";
    this.channel.addEventListener("message", (event) => this._receive(event.data));
    this.channel.addEventListener("close", () => this._ended("data channel closed"));
    this.pc.addEventListener("track", (event) => {
      if (event.track.kind !== "video" || !video) return;
      video.srcObject = event.streams[0] ?? new MediaStream([event.track]);
      video.play().catch(() => { /* autoplay refused: muted video may still start on its own */ });
    });
    this.pc.addEventListener("connectionstatechange", () => {
      if (this.pc.connectionState === "failed") this._ended("the peer connection failed");
    });
    this.ready = this._start();
    this.ready.catch(() => this.close());
  }

  get open() {
    return this.channel.readyState === "open";
  }

  _headers(extra = {}) {
    return this.token ? { ...extra, Authorization: `Bearer ${this.token}` } : extra;
  }

  async _start() {
    await this.pc.setLocalDescription(await this.pc.createOffer());
    await gathered(this.pc, GATHER_TIMEOUT_MS);
    const response = await fetch(this.url, {
      method: "POST", headers: this._headers({ "Content-Type": "application/sdp" }),
      body: this.pc.localDescription.sdp,
    });
    if (response.status !== 201) throw await httpError(response);
    const where = response.headers.get("Location");
    if (where) this.resource = new URL(where, location.href).pathname;
    const answer = await response.text();
    if (this.closed) throw new ProtocolError("internal", "closed while connecting");
    await this.pc.setRemoteDescription({ type: "answer", sdp: answer });
    return new Promise((resolve, reject) => {
      const timer = setTimeout(() => reject(new ProtocolError(
        "internal", `no welcome on the data channel within ${WELCOME_TIMEOUT_MS / 1000} s`)),
      WELCOME_TIMEOUT_MS);
      this._resolve = (welcome) => { clearTimeout(timer); resolve(welcome); };
      this._reject = (error) => { clearTimeout(timer); reject(error); };
    });
  }

  _ended(reason) {
    this._reject?.(new ProtocolError("internal", reason));
    if (this.closed) return;
    this.closed = true;
    this._emit("close", { code: 1006, reason });
  }

  _send(message, options = {}) {
    if (!this.open || !this.welcome) return false;  // as on the WebSocket: nothing before welcome
    this.channel.send(encode(message, options));
    return true;
  }

  /** Size and rate go to the video track; codec and JPEG fields mean nothing here. */
  request(fields) {
    const { codec, jpeg_quality, ...track } = fields;  // eslint-disable-line no-unused-vars
    return super.request(track);
  }

  /** Sample getStats() and keep the overlay's figures in `this.rtc`; the lip sync reads
   *  the same report. */
  async poll() {
    if (this.closed) return this.rtc;
    const report = await this.pc.getStats();
    this.lipSync?.update(report);
    const sample = rtcSample(report);
    if (sample) {
      this.rtc = { ...rtcSummary(this._sample, sample), lipSyncHoldMs: this.lipSync?.hold ?? null };
      this._sample = sample;
    }
    return this.rtc;
  }

  /** End the peer and DELETE the WHEP resource (keepalive: it still goes during unload). */
  close() {
    const resource = this.resource;
    this.resource = null;
    if (resource) {
      fetch(resource, { method: "DELETE", headers: this._headers(), keepalive: true })
        .catch(() => { /* the server drops a peer that goes silent anyway */ });
    }
    this._unwatch?.();
    this.channel.close();
    this.pc.close();
    if (!this.closed) {
      this.closed = true;
      this._reject?.(new ProtocolError("internal", "closed"));
      this._emit("close", { code: 1000, reason: "bye" });
    }
  }
}
