// Rolling client-side statistics for the overlay: frames per second, drive -> frame latency,
// ping round trip, bytes per second; plus the server's own `stats` message. Over WebRTC the
// frames are a video track the browser decodes: the figures come from getStats() (`rtc`, see
// rtcstats.js) instead, and the latency from the frames' stamps.
// Idle (nothing sent and no new frames for WINDOW_MS) reads "idle", not "fps: 0.0": the server
// renders only when something changes. The overlay sits under the picture and can be hidden
// (remembered in localStorage).

const WINDOW_MS = 2000;
// Over WebRTC the server repeats a still picture every 0.5 s (server/webrtc/track.py,
// REPEAT_AFTER_S): up to this decode rate, with nothing sent, the stream is idle.
const RTC_IDLE_FPS = 3;
export const OVERLAY_KEY = "telesplat.stats";  // localStorage: "hidden" or "shown"

function percentile(values, q) {
  if (!values.length) return null;
  const sorted = [...values].sort((a, b) => a - b);
  return sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
}

export class StreamStats {
  constructor() {
    this.frames = [];     // [time, bytes]
    this.latencies = [];  // [time, ms]
    this.rttMs = null;
    this.server = null;
    this.frameSize = null;
    this.framesTotal = 0;
    this.transport = null;  // "websocket" or "webrtc"
    this.rtc = null;        // rtcSummary() of the WebRTC peer
    this.inputAt = null;    // when this page last sent a drive, view, request or image
  }

  /** This page sent something that changes the picture. */
  input() {
    this.inputAt = performance.now();
  }

  /** A drive -> frame latency measured outside frame messages (WebRTC stamps). */
  latency(ms) {
    const now = performance.now();
    this.latencies.push([now, ms]);
    this._trim(this.latencies, now);
  }

  _trim(list, now) {
    while (list.length && now - list[0][0] > WINDOW_MS) list.shift();
  }

  frame(message) {
    const now = performance.now();
    this.framesTotal += 1;
    this.frames.push([now, message.data.byteLength]);
    if (message.latencyMs != null) this.latencies.push([now, message.latencyMs]);
    this.frameSize = `${message.width}x${message.height} ${message.codec}`;
    this._trim(this.frames, now);
    this._trim(this.latencies, now);
  }

  summary() {
    const now = performance.now();
    this._trim(this.frames, now);
    this._trim(this.latencies, now);
    const seconds = WINDOW_MS / 1000;
    const bytes = this.frames.reduce((sum, [, b]) => sum + b, 0);
    const ms = this.latencies.map(([, v]) => v);
    const quiet = this.inputAt === null || now - this.inputAt > WINDOW_MS;
    const rtcFps = this.rtc?.fps;
    const idle = quiet && (this.transport === "webrtc"
      ? rtcFps != null && rtcFps <= RTC_IDLE_FPS : this.frames.length === 0);
    return {
      idle,
      waiting: !quiet && this.transport !== "webrtc" && this.frames.length === 0,
      fps: this.frames.length / seconds,
      bytesPerS: bytes / seconds,
      latencyP50: percentile(ms, 0.5),
      latencyP95: percentile(ms, 0.95),
      rttMs: this.rttMs,
      frames: this.framesTotal,
      size: this.frameSize,
      server: this.server,
      transport: this.transport,
      rtc: this.rtc,
    };
  }
}

const fmt = (value, digits = 0, unit = "") => (value == null ? "–" : `${value.toFixed(digits)}${unit}`);

/** "idle", "waiting for frames" or the rate. */
function fpsText(s, fps) {
  if (s.idle) return "idle";
  if (s.waiting) return "waiting for frames";
  return fmt(fps, 1);
}

function rtcRows(s) {
  const rtc = s.rtc ?? {};
  return [
    ["transport", `webrtc${rtc.codec ? ` (${rtc.codec})` : ""}`],
    ["fps", fpsText(s, rtc.fps)],
    ["latency p50", fmt(s.latencyP50, 0, " ms")],
    ["latency p95", fmt(s.latencyP95, 0, " ms")],
    ["bit rate", fmt(rtc.bitrateKbps, 0, " kbit/s")],
    ["decoded", rtc.framesDecoded == null ? "–" : String(rtc.framesDecoded)],
    ["dropped", rtc.framesDropped == null ? "–" : String(rtc.framesDropped)],
    ["jitter", fmt(rtc.jitterMs, 1, " ms")],
    ["rtt", fmt(rtc.rttMs, 0, " ms")],
    ["lip-sync hold", fmt(rtc.lipSyncHoldMs, 0, " ms")],
    ["ping", fmt(s.rttMs, 0, " ms")],
    ["frame", rtc.size || "–"],
  ];
}

export function renderStats(element, s) {
  const rows = s.transport === "webrtc" ? rtcRows(s) : [
    ["transport", s.transport || "–"],
    ["fps", fpsText(s, s.fps)],
    ["latency p50", fmt(s.latencyP50, 0, " ms")],
    ["latency p95", fmt(s.latencyP95, 0, " ms")],
    ["ping", fmt(s.rttMs, 0, " ms")],
    ["data", `${fmt(s.bytesPerS / 1024, 0)} kB/s`],
    ["frames", String(s.frames)],
    ["frame", s.size || "–"],
  ];
  if (s.server) {
    rows.push(["server render", fmt(s.server.render_ms, 1, " ms")]);
    rows.push(["sessions", String(s.server.sessions)]);
  }
  element.replaceChildren(...rows.map(([k, v]) => {
    const row = document.createElement("div");
    row.dataset.stat = k;
    row.textContent = `${k}: ${v}`;
    return row;
  }));
}

/** The overlay's show / hide checkbox: its state comes from and goes to localStorage (shown
 *  unless hidden before). */
export function overlayToggle(checkbox, element, storage = window.localStorage) {
  const apply = () => { element.hidden = !checkbox.checked; };
  checkbox.checked = storage.getItem(OVERLAY_KEY) !== "hidden";
  apply();
  checkbox.addEventListener("change", () => {
    storage.setItem(OVERLAY_KEY, checkbox.checked ? "shown" : "hidden");
    apply();
  });
}
