// Mouse orbit around the avatar: drag = yaw/pitch, wheel = distance.
//
// `onChange(orbit, moving)` is called at most once per animation frame while dragging
// (moving = true, so the server may lower JPEG quality) and once when the drag ends.

const DEG_PER_PX = { yaw: 0.4, pitch: 0.3 };
const PITCH_LIMIT = 89;
const DISTANCE = { min: 0.4, max: 20 };

export class OrbitControl {
  constructor(element, onChange, orbit = {}) {
    this.orbit = { yaw_deg: 0, pitch_deg: 0, distance: 2.7, fov_y_deg: 30, ...orbit };
    this.onChange = onChange;
    this.dragging = false;
    this._pending = false;
    this._last = null;
    element.addEventListener("pointerdown", (e) => this._down(e, element));
    element.addEventListener("pointermove", (e) => this._move(e));
    element.addEventListener("pointerup", (e) => this._up(e, element));
    element.addEventListener("pointercancel", (e) => this._up(e, element));
    element.addEventListener("wheel", (e) => this._wheel(e), { passive: false });
  }

  _down(event, element) {
    if (event.button !== 0) return;
    this.dragging = true;
    this._last = [event.clientX, event.clientY];
    element.setPointerCapture?.(event.pointerId);
    event.preventDefault();
  }

  _move(event) {
    if (!this.dragging) return;
    const [x, y] = this._last;
    this._last = [event.clientX, event.clientY];
    let yaw = this.orbit.yaw_deg - (event.clientX - x) * DEG_PER_PX.yaw;
    yaw = ((((yaw + 180) % 360) + 360) % 360) - 180;  // keep it in [-180, 180)
    const pitch = this.orbit.pitch_deg + (event.clientY - y) * DEG_PER_PX.pitch;
    this.orbit.yaw_deg = yaw;
    this.orbit.pitch_deg = Math.min(PITCH_LIMIT, Math.max(-PITCH_LIMIT, pitch));
    this._schedule();
  }

  _up(event, element) {
    if (!this.dragging) return;
    this.dragging = false;
    element.releasePointerCapture?.(event.pointerId);
    this.onChange({ ...this.orbit }, false);  // the still view: full quality
  }

  _wheel(event) {
    event.preventDefault();
    const d = this.orbit.distance * Math.exp(event.deltaY * 0.001);
    this.orbit.distance = Math.min(DISTANCE.max, Math.max(DISTANCE.min, d));
    this.onChange({ ...this.orbit }, false);
  }

  // Mouse events come faster than frames: send one view per animation frame at most.
  _schedule() {
    if (this._pending) return;
    this._pending = true;
    requestAnimationFrame(() => {
      this._pending = false;
      if (this.dragging) this.onChange({ ...this.orbit }, true);
    });
  }
}
