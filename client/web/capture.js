// What the viewer keeps of the picture: fullscreen, a PNG snapshot of the current frame, a
// short WebM recording, and the background colour the server renders behind the avatar.
//
// The picture is the canvas (WebSocket frames) or the <video> (the WebRTC track), whichever
// is shown. Recordings use MediaRecorder on the captureStream() of a canvas the picture is
// copied onto at RECORD_FPS; they stop by themselves after `maxSeconds` (?record_s=N,
// 1..300, default 30), and their bit rate is fixed, so one recording holds at most about
// RECORD_BITS_PER_S / 8 x maxSeconds bytes (15 MB at 30 s).

import { stampCell } from "./rtcstats.js";

export const RECORD_SECONDS = { default: 30, min: 1, max: 300 };
export const RECORD_BITS_PER_S = 4_000_000;
const RECORD_FPS = 30;  // frames a second copied into a recording
const WEBM_TYPES = ["video/webm;codecs=vp9", "video/webm;codecs=vp8", "video/webm"];

/** The longest recording, from ?record_s= (seconds within RECORD_SECONDS); a bad value is
 *  reported to `onError(message)` and the default used. */
export function recordSeconds(search, onError = () => {}) {
  const raw = new URLSearchParams(search).get("record_s");
  if (raw === null) return RECORD_SECONDS.default;
  const value = Number(raw);
  if (raw.trim() === "" || !Number.isFinite(value) || value < RECORD_SECONDS.min
      || value > RECORD_SECONDS.max) {
    onError(`record_s must be ${RECORD_SECONDS.min} to ${RECORD_SECONDS.max} seconds, got `
      + `${JSON.stringify(raw)}: recordings stop after ${RECORD_SECONDS.default} s`);
    return RECORD_SECONDS.default;
  }
  return value;
}

/** Draw the picture at `width` x `height`. A stamped WebRTC frame (rtcstats.js: its top strip
 *  carries the drive seq, hidden on screen by a clip) gets the strip covered by the first row
 *  below it, so snapshots and recordings show what the viewer sees, not the stamp. */
function drawPicture(ctx, source, width, height) {
  ctx.drawImage(source, 0, 0, width, height);
  if (!(source instanceof HTMLVideoElement) || !source.style.clipPath) return;
  const strip = Math.min(height - 1, 2 * stampCell(width));
  if (strip > 0) ctx.drawImage(ctx.canvas, 0, strip, width, 1, 0, 0, width, strip);
}

/** "#rrggbb" -> [r, g, b] in [0, 1], the protocol's `background`. */
export function hexToRgb(hex) {
  const m = /^#([0-9a-f]{2})([0-9a-f]{2})([0-9a-f]{2})$/i.exec(hex);
  if (!m) throw new RangeError(`not a #rrggbb colour: ${JSON.stringify(hex)}`);
  return m.slice(1).map((h) => parseInt(h, 16) / 255);
}

const stamp = () => new Date().toISOString().replace(/[:.]/g, "-").slice(0, 19);

export class Capture {
  /** `picture()` gives the element shown now (canvas or video); `onSaved({kind, blob, url,
   *  name, ...})` is told of each snapshot and recording. */
  constructor(stage, picture, { maxSeconds = RECORD_SECONDS.default, onSaved = () => {} } = {}) {
    this.stage = stage;
    this.picture = picture;
    this.maxSeconds = maxSeconds;
    this.onSaved = onSaved;
    this.recorder = null;
    this.recordedChunks = 0;  // of the current (or last) recording
    this.onRecording = () => {};  // (recording: bool) for the button
  }

  get fullscreen() {
    return document.fullscreenElement === this.stage;
  }

  async toggleFullscreen() {
    if (this.fullscreen) await document.exitFullscreen();
    else await this.stage.requestFullscreen();
  }

  /** A PNG of the frame shown, at the frame's own size (not the CSS size). */
  async snapshot() {
    const source = this.picture();
    let canvas = source;
    if (source instanceof HTMLVideoElement) {
      if (!source.videoWidth) throw new Error("no video frame yet");
      canvas = document.createElement("canvas");
      canvas.width = source.videoWidth;
      canvas.height = source.videoHeight;
      drawPicture(canvas.getContext("2d"), source, canvas.width, canvas.height);
    }
    const blob = await new Promise((resolve, reject) => canvas.toBlob(
      (b) => (b ? resolve(b) : reject(new Error("the frame could not be encoded"))), "image/png"));
    return this._saved({ kind: "snapshot", blob, name: `telesplat-${stamp()}.png`,
      width: canvas.width, height: canvas.height });
  }

  get recording() {
    return this.recorder !== null && this.recorder.state !== "inactive";
  }

  /** Start recording what is shown; resolves with the recording when it stops (the button, or
   *  after `maxSeconds`). */
  record() {
    if (this.recording) throw new Error("already recording");
    // The frames are drawn onto a canvas of the recording's own at RECORD_FPS: the page's
    // canvas has frames only when one arrives (a still avatar would record nothing), and the
    // video's size may change mid-way; this one keeps the size the recording started with.
    const source = this.picture();
    const width = source.videoWidth ?? source.width;
    const height = source.videoHeight ?? source.height;
    if (!width || !height) throw new Error("nothing to record yet");
    const canvas = Object.assign(document.createElement("canvas"), { width, height });
    const ctx = canvas.getContext("2d");
    const draw = () => drawPicture(ctx, source, width, height);
    draw();
    const stream = canvas.captureStream(RECORD_FPS);
    const ticker = setInterval(draw, 1000 / RECORD_FPS);
    const mimeType = WEBM_TYPES.find((t) => MediaRecorder.isTypeSupported(t));
    if (!mimeType) throw new Error("this browser cannot record WebM");
    const recorder = new MediaRecorder(stream, { mimeType, videoBitsPerSecond: RECORD_BITS_PER_S });
    const chunks = [];
    this.recordedChunks = 0;
    const started = performance.now();
    this.recorder = recorder;
    const done = new Promise((resolve, reject) => {
      recorder.addEventListener("dataavailable", (e) => {
        if (e.data.size) chunks.push(e.data);
        this.recordedChunks = chunks.length;  // one a second while it records
      });
      recorder.addEventListener("error", (e) => reject(e.error ?? new Error("recording failed")));
      recorder.addEventListener("stop", () => {
        clearTimeout(limit);
        clearInterval(ticker);
        this.onRecording(false);
        const blob = new Blob(chunks, { type: "video/webm" });
        if (!blob.size) {
          reject(new Error("no frame was recorded"));
          return;
        }
        resolve(this._saved({ kind: "recording", blob, name: `telesplat-${stamp()}.webm`,
          seconds: (performance.now() - started) / 1000 }));
      });
    });
    const limit = setTimeout(() => this.stop(), this.maxSeconds * 1000);
    recorder.start(1000);  // a chunk a second: a tab closed mid-way loses at most that
    this.onRecording(true);
    return done;
  }

  stop() {
    if (this.recording) this.recorder.stop();
  }

  _saved(item) {
    const saved = { ...item, url: URL.createObjectURL(item.blob), size: item.blob.size };
    this.onSaved(saved);
    return saved;
  }
}

/** A download link for a saved capture, newest first in `list`, at most `keep` of them (older
 *  ones are removed and their blob URLs revoked). */
export function showSaved(list, saved, keep = 5) {
  const link = Object.assign(document.createElement("a"), {
    href: saved.url, download: saved.name,
    textContent: `${saved.name} (${Math.max(1, Math.round(saved.size / 1024))} kB`
      + `${saved.seconds ? `, ${saved.seconds.toFixed(1)} s` : ""})`,
  });
  link.dataset.kind = saved.kind;
  list.prepend(link);
  while (list.childElementCount > keep) {
    URL.revokeObjectURL(list.lastElementChild.href);
    list.lastElementChild.remove();
  }
  return link;
}
