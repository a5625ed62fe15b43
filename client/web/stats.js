// Rolling client-side statistics for the overlay: frames per second, drive -> frame latency,
// ping round trip, bytes per second; plus the server's own `stats` message. Over WebRTC the
// frames are a video track the browser decodes: the figures come from getStats() (`rtc`, see
// rtcstats.js) instead.

const WINDOW_MS = 2000;

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
    return {
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

function rtcRows(s) {
  const rtc = s.rtc ?? {};
  return [
    ["transport", `webrtc${rtc.codec ? ` (${rtc.codec})` : ""}`],
    ["fps", fmt(rtc.fps, 1)],
    ["bit rate", fmt(rtc.bitrateKbps, 0, " kbit/s")],
    ["decoded", rtc.framesDecoded == null ? "–" : String(rtc.framesDecoded)],
    ["dropped", rtc.framesDropped == null ? "–" : String(rtc.framesDropped)],
    ["jitter", fmt(rtc.jitterMs, 1, " ms")],
    ["rtt", fmt(rtc.rttMs, 0, " ms")],
    ["ping", fmt(s.rttMs, 0, " ms")],
    ["frame", rtc.size || "–"],
  ];
}

export function renderStats(element, s) {
  const rows = s.transport === "webrtc" ? rtcRows(s) : [
    ["transport", s.transport || "–"],
    ["fps", fmt(s.fps, 1)],
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
