// "Make my avatar": record the webcam with MediaRecorder (WebM) while on-screen guidance says
// what to do and when (face the camera, turn left, turn right, smile, open the hands), show
// the recorded length, upload the recording as an enrollment job (POST /v1/jobs, part
// "video"), follow the job's events and say when the new avatar is ready.
// The recording lasts ?enroll_s= seconds (ENROLL_SECONDS: 5..120, default 30) and stops by
// itself; ?enroll_config= (JSON EnrollConfig fields, e.g. {"iterations": 2000}) overrides the
// server's enrollment defaults within its limits.

export const ENROLL_SECONDS = { default: 30, min: 5, max: 120 };
export const ENROLL_BITS_PER_S = 2_500_000;  // ~9 MB for 30 s, well inside the server's limit
const WEBM_TYPES = ["video/webm;codecs=vp8", "video/webm;codecs=vp9", "video/webm"];
const TICK_MS = 200;          // how often the guidance and the length are updated
const MAX_EVENT_STREAMS = 100;  // reconnections of the job's event stream (each <= 10 min)

// What to do, as fractions of the recording: the pipeline needs both sides of the head and
// body, a few expressions and open hands (docs/jobs.md, "Enrollment").
const GUIDANCE = [
  [0.0, "Face the camera, arms relaxed"],
  [0.1, "Turn slowly to your left"],
  [0.3, "Turn slowly back and on to your right"],
  [0.55, "Come back to face the camera"],
  [0.65, "Smile, then open your mouth"],
  [0.8, "Open your hands toward the camera"],
];

/** The recording's length in seconds, from ?enroll_s= (within ENROLL_SECONDS); a bad value
 *  is reported to `onError(message)` and the default used. */
export function enrollSeconds(search, onError = () => {}) {
  const raw = new URLSearchParams(search).get("enroll_s");
  if (raw === null) return ENROLL_SECONDS.default;
  const value = Number(raw);
  if (raw.trim() === "" || !Number.isFinite(value) || value < ENROLL_SECONDS.min
      || value > ENROLL_SECONDS.max) {
    onError(`enroll_s must be ${ENROLL_SECONDS.min} to ${ENROLL_SECONDS.max} seconds, got `
      + `${JSON.stringify(raw)}: recording ${ENROLL_SECONDS.default} s`);
    return ENROLL_SECONDS.default;
  }
  return value;
}

/** ?enroll_config= as an object (null when absent); a bad value is reported and ignored. */
export function enrollConfig(search, onError = () => {}) {
  const raw = new URLSearchParams(search).get("enroll_config");
  if (raw === null) return null;
  try {
    const value = JSON.parse(raw);
    if (value && typeof value === "object" && !Array.isArray(value)) return value;
  } catch { /* reported below */ }
  onError(`enroll_config must be a JSON object, got ${JSON.stringify(raw)}: using the server's`);
  return null;
}

/** The guidance for a `seconds` long recording: [{text, start, end}] in seconds. */
export function guidanceSteps(seconds) {
  return GUIDANCE.map(([at, text], i) => ({
    text, start: at * seconds, end: (GUIDANCE[i + 1]?.[0] ?? 1) * seconds,
  }));
}

/** The step at `t` seconds (the last one past the end). */
export function stepAt(steps, t) {
  const i = steps.findIndex((s) => t < s.end);
  return i < 0 ? steps.length - 1 : i;
}

/** 7.4 -> "0:07", 75 -> "1:15". */
export function formatLength(seconds) {
  const s = Math.max(0, Math.floor(seconds));
  return `${Math.floor(s / 60)}:${String(s % 60).padStart(2, "0")}`;
}

/** Server-sent events in `text`: {events: [{id, event, data}], rest} (rest: an unfinished
 *  event, to be completed by the next chunk). `data` is parsed as JSON when it is JSON. */
export function parseSse(text) {
  const blocks = text.replace(/\r\n?/g, "\n").split("\n\n");
  const rest = blocks.pop();
  const events = [];
  for (const block of blocks) {
    let id = null;
    let event = "message";
    const data = [];
    for (const line of block.split("\n")) {
      if (!line || line.startsWith(":")) continue;
      const colon = line.indexOf(":");
      const field = colon < 0 ? line : line.slice(0, colon);
      const value = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
      if (field === "id") id = value;
      else if (field === "event") event = value;
      else if (field === "data") data.push(value);
    }
    if (!data.length && id === null) continue;
    let parsed = data.join("\n");
    try { parsed = JSON.parse(parsed); } catch { /* plain text */ }
    events.push({ id, event, data: parsed });
  }
  return { events, rest };
}

/** A refused upload's words: the server's {reason, message, what_to_do} or its text. */
export function refusalText(status, detail) {
  if (detail && typeof detail === "object" && detail.message) {
    return `${detail.message} ${detail.what_to_do ?? ""}`.trim();
  }
  return `${status} ${typeof detail === "string" ? detail : JSON.stringify(detail)}`;
}

/** The status line for a job event: "training: 42%", or null when it says nothing new. */
export function progressText(event, data) {
  if (event === "end" || event === "state") {
    if (data?.state === "succeeded") return "done: your avatar is ready";
    if (data?.state === "failed") return `failed: ${data.error ?? "see the job's log"}`;
    if (data?.state === "cancelled") return "cancelled";
    if (data?.state === "queued") return "waiting for the server…";
    if (data?.state === "running") return "started";
    return null;
  }
  if (typeof data?.progress === "number") {
    const stage = data.stage ?? event;
    return `${stage}: ${Math.floor(data.progress * 100)}%`;
  }
  return null;
}

export class Enrollment {
  /** `ui`: the panel's elements {guide, steps, length, preview, status, progress};
   *  `token`: the bearer token; `onChange(state)` after every change of `state`. */
  constructor(ui, token, { seconds = ENROLL_SECONDS.default, config = null,
    onChange = () => {} } = {}) {
    this.ui = ui;
    this.token = token;
    this.seconds = seconds;
    this.config = config;
    this.onChange = onChange;
    this.steps = guidanceSteps(seconds);
    this.state = { phase: "idle", seconds: 0, bytes: 0, step: null, jobId: null, events: [],
      progress: 0, avatarId: null, error: null };
    this.recorder = null;
    this.stream = null;
    this.blob = null;
    this.abort = null;
  }

  set(changes) {
    Object.assign(this.state, changes);
    this.onChange(this.state);
  }

  status(text, kind = "info") {
    this.ui.status.textContent = text;
    this.ui.status.className = kind;
  }

  get recording() {
    return this.recorder !== null && this.recorder.state === "recording";
  }

  async record() {
    if (this.recording) return;
    if (typeof MediaRecorder !== "function" || !navigator.mediaDevices?.getUserMedia) {
      throw new Error("this browser cannot record the camera (needs https or localhost)");
    }
    this.stream = await navigator.mediaDevices.getUserMedia({
      video: { width: { ideal: 640 }, height: { ideal: 480 } }, audio: false,
    });
    this.ui.preview.srcObject = this.stream;
    this.ui.preview.hidden = false;
    await this.ui.preview.play().catch(() => {});
    const mimeType = WEBM_TYPES.find((t) => MediaRecorder.isTypeSupported(t)) || "";
    const chunks = [];
    this.recorder = new MediaRecorder(this.stream,
      { mimeType, videoBitsPerSecond: ENROLL_BITS_PER_S });
    this.recorder.ondataavailable = (e) => { if (e.data.size) chunks.push(e.data); };
    const stopped = new Promise((resolve) => { this.recorder.onstop = resolve; });
    this.blob = null;
    this.recorder.start(1000);  // a chunk a second: the length shown grows as it records
    const started = performance.now();
    this.set({ phase: "recording", seconds: 0, bytes: 0, jobId: null, events: [],
      progress: 0, avatarId: null, error: null });
    this.renderSteps();
    const timer = setInterval(() => {
      const t = (performance.now() - started) / 1000;
      if (t >= this.seconds) this.stop();
      this.tick(t, chunks.reduce((n, c) => n + c.size, 0));
    }, TICK_MS);
    await stopped;
    clearInterval(timer);
    const seconds = Math.min(this.seconds, (performance.now() - started) / 1000);
    this.blob = new Blob(chunks, { type: this.recorder.mimeType || "video/webm" });
    this.stream.getTracks().forEach((track) => track.stop());
    this.ui.preview.srcObject = null;
    this.ui.preview.hidden = true;
    this.ui.guide.textContent = `Recorded ${formatLength(seconds)}: upload it to make your avatar`;
    this.ui.length.textContent = `${formatLength(seconds)} recorded`
      + ` (${(this.blob.size / 1e6).toFixed(1)} MB)`;
    this.set({ phase: "recorded", seconds, bytes: this.blob.size, step: null });
    return this.blob;
  }

  stop() {
    if (this.recording) this.recorder.stop();
  }

  tick(t, bytes) {
    const i = stepAt(this.steps, t);
    const step = this.steps[i];
    this.ui.guide.textContent = `${step.text} (${Math.max(0, Math.ceil(step.end - t))} s)`;
    this.ui.length.textContent = `${formatLength(t)} of ${formatLength(this.seconds)}`;
    [...this.ui.steps.children].forEach((li, k) => {
      li.className = k < i ? "done" : k === i ? "current" : "";
    });
    if (this.state.step !== i || Math.floor(t) !== Math.floor(this.state.seconds)) {
      this.set({ step: i, seconds: t, bytes });
    }
  }

  renderSteps() {
    this.ui.steps.replaceChildren(...this.steps.map((s) => Object.assign(
      document.createElement("li"),
      { textContent: `${formatLength(s.start)} ${s.text}` })));
  }

  /** Upload the recording as an enrollment job; the job as the server answered it. */
  async upload(name) {
    if (!this.blob) throw new Error("record a video first");
    const form = new FormData();
    form.append("video", this.blob, "enrollment.webm");
    form.append("config", JSON.stringify(this.config ?? "enroll"));
    if (name) form.append("name", name);
    this.set({ phase: "uploading", error: null });
    this.status(`uploading ${(this.blob.size / 1e6).toFixed(1)} MB…`);
    const response = await fetch("/v1/jobs", {
      method: "POST", body: form,
      headers: this.token ? { Authorization: `Bearer ${this.token}` } : {},
    });
    let body = null;
    try { body = await response.json(); } catch { /* not JSON */ }
    if (!response.ok) {
      const text = refusalText(response.status, body?.detail ?? response.statusText);
      this.set({ phase: "refused", error: text });
      this.status(`not accepted: ${text}`, "error");
      const error = new Error(text);
      error.status = response.status;
      throw error;
    }
    this.set({ phase: "running", jobId: body.id });
    this.status("accepted: waiting for the server…");
    this.ui.progress.hidden = false;
    this.ui.progress.value = 0;
    return body;
  }

  /** Follow the job's events until it ends (bounded reconnections); its end event's data. */
  async follow(jobId) {
    let after = 0;
    this.abort = new AbortController();
    for (let i = 0; i < MAX_EVENT_STREAMS; i += 1) {
      const response = await fetch(`/v1/jobs/${jobId}/events?after=${after}`, {
        headers: { Accept: "text/event-stream",
          ...(this.token ? { Authorization: `Bearer ${this.token}` } : {}) },
        signal: this.abort.signal,
      });
      if (!response.ok) throw new Error(`job events: HTTP ${response.status}`);
      const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        const { events, rest } = parseSse(buffer + value);
        buffer = rest;
        for (const e of events) {
          if (e.id && /^\d+$/.test(e.id)) after = Number(e.id);
          const end = this.onEvent(e);
          if (end) {
            reader.cancel().catch(() => {});
            return end;
          }
        }
      }
    }
    throw new Error("the job's events stopped before it ended");
  }

  onEvent({ event, data }) {
    this.state.events.push({ event, ...(data && typeof data === "object" ? data : {}) });
    const text = progressText(event, data);
    if (typeof data?.progress === "number") {
      this.ui.progress.value = data.progress;
      this.set({ progress: data.progress });
    }
    if (text) this.status(text, data?.state === "failed" ? "error" : "info");
    if (event !== "end") {
      this.onChange(this.state);
      return null;
    }
    this.ui.progress.value = data.state === "succeeded" ? 1 : this.ui.progress.value;
    this.set({ phase: data.state, avatarId: data.avatar_id ?? null, error: data.error ?? null });
    return data;
  }

  close() {
    this.stop();
    this.abort?.abort();
  }
}
