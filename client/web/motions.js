// Built-in motion clips from the server (GET /v1/motions, GET /v1/motions/{name}), played by
// driving one frame per clip frame at the clip's rate.

const FPS = 30;

// JSON lists -> Float32Array (flattened: the protocol takes fixed shapes flat too).
function toTyped(frame) {
  const out = {};
  for (const [family, fields] of Object.entries(frame)) {
    if (typeof fields !== "object" || fields === null) continue;
    out[family] = {};
    for (const [name, value] of Object.entries(fields)) {
      out[family][name] = Float32Array.from([value].flat(4));
    }
  }
  return out;
}

// A frame may hold SMPL-X fields directly; group them under "smplx".
function familyKeyed(frame) {
  const families = ["smplx", "flame", "mano_left", "mano_right"];
  const out = {};
  for (const [key, value] of Object.entries(frame)) {
    if (families.includes(key)) out[key] = value;
    else (out.smplx ||= {})[key] = value;
  }
  return out;
}

export class MotionPlayer {
  constructor(api, drive) {
    this.api = api;        // (path) => Promise<json>
    this.drive = drive;    // (families, reset) => void
    this.cache = new Map();
    this.playing = null;   // {name, frames, fps, start, index}
    this.loop = false;
    this.onState = () => {};
  }

  async list() {
    const body = await this.api("/v1/motions");
    return Array.isArray(body) ? body : body.motions;
  }

  async load(name, avatar) {
    const key = `${avatar}/${name}`;
    if (!this.cache.has(key)) {
      const query = new URLSearchParams({ fps: String(FPS) });
      if (avatar) query.set("avatar", avatar);
      const body = await this.api(`/v1/motions/${encodeURIComponent(name)}?${query}`);
      const frames = (Array.isArray(body) ? body : body.frames).map((f) => toTyped(familyKeyed(f)));
      this.cache.set(key, { frames, fps: body.fps || FPS });
    }
    return this.cache.get(key);
  }

  async play(name, avatar) {
    const clip = await this.load(name, avatar);
    this.playing = { name, ...clip, start: performance.now(), index: -1 };
    this.onState(this.playing);
    this._tick();
  }

  stop() {
    this.playing = null;
    this.onState(null);
  }

  _tick() {
    const p = this.playing;
    if (!p) return;
    let index = Math.floor(((performance.now() - p.start) / 1000) * p.fps);
    if (index >= p.frames.length) {
      if (!this.loop) {
        this.drive(p.frames[p.frames.length - 1], false);
        this.stop();
        return;
      }
      p.start = performance.now();
      index = 0;
    }
    if (index !== p.index) {
      p.index = index;
      this.drive(p.frames[index], false);
    }
    requestAnimationFrame(() => this._tick());
  }
}
