// The viewpoint: orbit (drag), zoom toward the face (wheel), pan (right- or shift-drag), reset
// (double-click or the button), all as the `orbit` of the protocol's `view`.
//
// The default view is the welcome's `framing` (the server frames the scene at rest: every
// upper body, head to the cut, both hands). Zooming in slides the orbit's target from the
// framing's target to the face, linearly with the distance, and stops at the framing's
// `min_distance`: both ends show the whole head, and the edges of the view move linearly in
// between, so no zoom level cuts it. A server without `framing` gets the old orbit (the
// server's default target, 2.7 m).
//
// `onChange(orbit, moving)` is called at most once per animation frame while dragging
// (moving = true, so the server may lower JPEG quality) and once when the drag ends.

import { DEFAULT_LIMITS } from "./protocol.js";

const DEG_PER_PX = { yaw: 0.4, pitch: 0.3 };
const PITCH_LIMIT = 89;
const WHEEL_ZOOM = 0.001;  // distance x exp(deltaY * this): a wheel notch (100) is ~10%
const FALLBACK = { yaw_deg: 0, pitch_deg: 0, distance: 2.7, fov_y_deg: 30 };

const add = (a, b) => a.map((v, i) => v + b[i]);
const scale = (a, s) => a.map((v) => v * s);
const lerp = (a, b, t) => a.map((v, i) => v + (b[i] - v) * t);
const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));

/** The camera's right and up directions (world) for an orbit's yaw and pitch, as
 *  avatar_core.render.camera.orbit places it. */
export function screenAxes(yawDeg, pitchDeg) {
  const yaw = (yawDeg * Math.PI) / 180;
  const pitch = (pitchDeg * Math.PI) / 180;
  const right = [Math.cos(yaw), 0, -Math.sin(yaw)];
  // up = right x forward, forward = -(sin y cos p, sin p, cos y cos p)
  const up = [-Math.sin(pitch) * Math.sin(yaw), Math.cos(pitch), -Math.sin(pitch) * Math.cos(yaw)];
  return { right, up };
}

/** Where zoom puts the target: the framing's target at its distance or farther, the face at
 *  `min_distance`, linear in between. */
export function zoomTarget(framing, distance) {
  const span = framing.distance - framing.min_distance;
  const t = span > 0 ? clamp((framing.distance - distance) / span, 0, 1) : 0;
  return lerp(framing.target, framing.face, t);
}

export class ViewControl {
  /** `elements`: what to listen on (the canvas and the video: the bar's buttons stay apart). */
  constructor(elements, onChange) {
    this.onChange = onChange;
    this.framing = null;
    this.limits = DEFAULT_LIMITS;
    this.pan = [0, 0, 0];  // world offset added to the zoom's target
    this.orbit = { ...FALLBACK };
    this.dragging = null;  // "orbit" | "pan" while a button is down
    this._pending = false;
    this._last = null;
    for (const element of [elements].flat()) {
      element.addEventListener("pointerdown", (e) => this._down(e, element));
      element.addEventListener("pointermove", (e) => this._move(e, element));
      element.addEventListener("pointerup", (e) => this._up(e, element));
      element.addEventListener("pointercancel", (e) => this._up(e, element));
      element.addEventListener("wheel", (e) => this._wheel(e), { passive: false });
      element.addEventListener("dblclick", () => this.reset());
      element.addEventListener("contextmenu", (e) => e.preventDefault());  // right-drag pans
    }
  }

  /** The welcome's framing (or null) and limits: the default view; the view goes back to it. */
  setFraming(framing, limits = DEFAULT_LIMITS) {
    this.framing = framing ?? null;
    this.limits = limits;
    this.reset({ send: false });
  }

  get minDistance() {
    return Math.max(this.limits.min_orbit_distance_m, this.framing?.min_distance ?? 0);
  }

  /** Back to the default framing: front view, no pan, the framing's distance. */
  reset({ send = true } = {}) {
    this.pan = [0, 0, 0];
    const f = this.framing;
    this.orbit = f ? { yaw_deg: 0, pitch_deg: 0, distance: f.distance, fov_y_deg: f.fov_y_deg }
      : { ...FALLBACK };
    this._place();
    if (send) this.onChange(this.current(), false);
  }

  /** The orbit to send: a copy, with the target where zoom and pan put it. */
  current() {
    const orbit = { ...this.orbit };
    if (orbit.target) orbit.target = [...orbit.target];
    return orbit;
  }

  zoomTo(distance) {
    this.orbit.distance = clamp(distance, this.minDistance, this.limits.max_orbit_distance_m);
    this._place();
  }

  /** Move the target by a drag of (dx, dy) CSS pixels on an element `heightPx` tall: the
   *  point under the cursor stays under it (at the target's depth). */
  panBy(dx, dy, heightPx) {
    const { right, up } = screenAxes(this.orbit.yaw_deg, this.orbit.pitch_deg);
    const metresPerPx = (2 * this.orbit.distance
      * Math.tan((this.orbit.fov_y_deg * Math.PI) / 360)) / Math.max(1, heightPx);
    this.pan = add(this.pan, add(scale(right, -dx * metresPerPx), scale(up, dy * metresPerPx)));
    this._place();
  }

  _place() {
    if (!this.framing) {  // the server's default target, moved by the pan only
      delete this.orbit.target;
      if (this.pan.some((v) => v !== 0)) this.orbit.target = [...this.pan];
      return;
    }
    let target = add(zoomTarget(this.framing, this.orbit.distance), this.pan);
    const norm = Math.hypot(...target);
    const max = this.limits.max_position_m;
    if (norm > max) target = scale(target, max / norm);  // the server refuses farther
    this.orbit.target = target;
  }

  _down(event, element) {
    if (event.button !== 0 && event.button !== 2) return;
    this.dragging = event.button === 2 || event.shiftKey ? "pan" : "orbit";
    this._last = [event.clientX, event.clientY];
    try {
      element.setPointerCapture?.(event.pointerId);
    } catch { /* a synthetic event's pointer: nothing to capture */ }
    event.preventDefault();
  }

  _move(event, element) {
    if (!this.dragging) return;
    const [x, y] = this._last;
    const dx = event.clientX - x;
    const dy = event.clientY - y;
    this._last = [event.clientX, event.clientY];
    if (this.dragging === "pan") {
      this.panBy(dx, dy, element.getBoundingClientRect().height);
    } else {
      let yaw = this.orbit.yaw_deg - dx * DEG_PER_PX.yaw;
      yaw = ((((yaw + 180) % 360) + 360) % 360) - 180;  // keep it in [-180, 180)
      this.orbit.yaw_deg = yaw;
      this.orbit.pitch_deg = clamp(this.orbit.pitch_deg + dy * DEG_PER_PX.pitch,
        -PITCH_LIMIT, PITCH_LIMIT);
    }
    this._schedule();
  }

  _up(event, element) {
    if (!this.dragging) return;
    this.dragging = null;
    element.releasePointerCapture?.(event.pointerId);
    this.onChange(this.current(), false);  // the still view: full quality
  }

  _wheel(event) {
    event.preventDefault();
    this.zoomTo(this.orbit.distance * Math.exp(event.deltaY * WHEEL_ZOOM));
    this.onChange(this.current(), false);
  }

  // Mouse events come faster than frames: send one view per animation frame at most.
  _schedule() {
    if (this._pending) return;
    this._pending = true;
    requestAnimationFrame(() => {
      this._pending = false;
      if (this.dragging) this.onChange(this.current(), true);
    });
  }
}

/** Keep `elements` (the canvas, the video) inside the window: their CSS max height is the
 *  room left below the stage's top edge, updated on resize and when the page above reflows. */
export function fitToViewport(stage, { margin = 16 } = {}) {
  const fit = () => {
    const top = stage.getBoundingClientRect().top + window.scrollY;
    // What sits under the picture in the stage (the stats, the button bar) must fit too.
    let below = 0;
    for (const child of stage.children) {
      if (child.tagName === "CANVAS" || child.tagName === "VIDEO" || child.hidden) continue;
      const style = getComputedStyle(child);
      if (style.display === "none" || style.position === "absolute") continue;
      below += child.offsetHeight + parseFloat(style.marginTop) + parseFloat(style.marginBottom);
    }
    const room = Math.max(64, window.innerHeight - top - margin - below);
    stage.style.setProperty("--stage-max-height", `${Math.floor(room)}px`);
  };
  window.addEventListener("resize", fit);
  new ResizeObserver(fit).observe(document.body);
  fit();
  return fit;
}
