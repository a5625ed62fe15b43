// Rolling client-side statistics for the overlay: frames per second, drive -> frame latency,
// ping round trip, bytes per second; plus the server's own `stats` message.

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
    };
  }
}

const fmt = (value, digits = 0, unit = "") => (value == null ? "–" : `${value.toFixed(digits)}${unit}`);

export function renderStats(element, s) {
  const rows = [
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
