// Sliders for the jaw, the expression coefficients and the hands, turned into partial
// SMPL-X updates (only what the slider touches is sent). Slider ranges stay inside the value
// ranges of the session's limits (sent in welcome), which the server enforces.

import { DEFAULT_LIMITS } from "./protocol.js";

const EXPRESSION_SLIDERS = 10;  // an avatar that names no expressions: its first ten
// SMPL-X hand joints: index, middle, pinky, ring (3 each), then the thumb (3).
const FINGER_JOINTS = 12;

// A range [min, max] cut to [-bound, bound].
function within(range, bound) {
  return { ...range, min: Math.max(range.min, -bound), max: Math.min(range.max, bound) };
}

function slider(container, label, { min, max, step = 0.01, value = 0 }, onInput) {
  const row = document.createElement("label");
  row.className = "slider";
  const name = document.createElement("span");
  name.textContent = label;
  const input = Object.assign(document.createElement("input"),
    { type: "range", min, max, step, value });
  input.dataset.param = label;
  const shown = document.createElement("output");
  shown.textContent = Number(value).toFixed(2);
  input.addEventListener("input", () => {
    shown.textContent = Number(input.value).toFixed(2);
    onInput(Number(input.value));
  });
  row.append(name, input, shown);
  container.append(row);
  return input;
}

// Fingers flex about z (the right hand +z, the mirrored left hand -z); the thumb half as much.
function handPose(curl, sign) {
  const pose = new Float32Array(45);
  for (let j = 0; j < 15; j += 1) pose[3 * j + 2] = sign * curl * (j < FINGER_JOINTS ? 1 : 0.5);
  return pose;
}

export class Controls {
  /** `send(families)` receives partial updates, e.g. {smplx: {jaw_pose: Float32Array}}. */
  constructor(container, send) {
    this.container = container;
    this.send = send;
    this.jaw = { open: 0, side: 0 };
    this.expression = new Float32Array(EXPRESSION_SLIDERS);
    this.inputs = [];
  }

  /** `expressionNames`: the avatar's (welcome.avatar.expression_names), one slider each;
   *  none: ten sliders "expression 0" … "expression 9". */
  build(expressionNames = [], limits = DEFAULT_LIMITS) {
    this.container.replaceChildren();
    const count = expressionNames.length || EXPRESSION_SLIDERS;
    this.expression = new Float32Array(count);
    const angle = (range) => within(range, limits.max_rotation_rad);
    const coefficient = (range) => within(range, limits.max_coefficient);
    const jaw = () => this.send({ smplx: { jaw_pose: new Float32Array([this.jaw.open, this.jaw.side, 0]) } });
    this.inputs = [
      slider(this.container, "jaw open", angle({ min: 0, max: 0.5 }), (v) => { this.jaw.open = v; jaw(); }),
      slider(this.container, "jaw side", angle({ min: -0.2, max: 0.2 }), (v) => { this.jaw.side = v; jaw(); }),
    ];
    for (let i = 0; i < count; i += 1) {
      const label = expressionNames[i] || `expression ${i}`;
      this.inputs.push(slider(this.container, label, coefficient({ min: -1.5, max: 1.5 }), (v) => {
        this.expression[i] = v;
        this.send({ smplx: { expression: Float32Array.from(this.expression) } });
      }));
    }
    for (const [side, sign] of [["left", -1], ["right", 1]]) {
      this.inputs.push(slider(this.container, `${side} hand curl`, angle({ min: -0.3, max: 1.5 }), (v) => {
        this.send({ smplx: { [`${side}_hand_pose`]: handPose(v, sign) } });
      }));
    }
  }

  reset() {
    this.jaw = { open: 0, side: 0 };
    this.expression.fill(0);
    for (const input of this.inputs) {
      input.value = 0;
      input.nextElementSibling.textContent = "0.00";
    }
  }
}
