// Webcam driving: grab camera frames, encode them as JPEG and send `image` messages at a
// capped rate, each with its capture time (the clock of the page's drives and voice: the
// frames tracked from it carry it back, and the voice waits for them). The server tracks them into parameters and answers each with `tracked`
// (whether it found a person), or with error `unsupported` when its landmark models are
// missing.

const MAX_FPS = 10;        // the tracker needs no more, and uplinks are often thin
const WIDTH = 320;         // small frames: landmarks need little, the message stays small
const JPEG_QUALITY = 0.7;

export class Webcam {
  constructor(send) {
    this.send = send;  // (Uint8Array, tCaptureS) => void
    this.frameCapturedMs = null;  // the shown camera frame's capture time (performance.now())
    this.stream = null;
    this.timer = null;
    this.busy = false;
    this.video = document.createElement("video");
    this.video.muted = true;
    this.video.playsInline = true;
    this.canvas = document.createElement("canvas");
  }

  get running() {
    return this.stream !== null;
  }

  async start() {
    if (!navigator.mediaDevices?.getUserMedia) {
      throw new Error("this browser gives no camera access (needs https or localhost)");
    }
    this.stream = await navigator.mediaDevices.getUserMedia({
      video: { width: { ideal: 640 }, height: { ideal: 480 } }, audio: false,
    });
    this.video.srcObject = this.stream;
    await this.video.play();
    this._followFrames();
    this.timer = setInterval(() => this._grab(), 1000 / MAX_FPS);
  }

  stop() {
    clearInterval(this.timer);
    this.timer = null;
    this.stream?.getTracks().forEach((track) => track.stop());
    this.stream = null;
    this.video.srcObject = null;
    this.frameCapturedMs = null;
  }

  /** The camera's own capture time of each frame the video shows, where the browser gives it
   *  (requestVideoFrameCallback); else the moment it is grabbed stands in. */
  _followFrames() {
    if (typeof this.video.requestVideoFrameCallback !== "function") return;
    const onFrame = (now, meta) => {
      this.frameCapturedMs = meta.captureTime ?? now;
      if (this.running) this.video.requestVideoFrameCallback(onFrame);
    };
    this.video.requestVideoFrameCallback(onFrame);
  }

  _grab() {
    // Skip a tick rather than queue encodes when the browser is slow.
    if (this.busy || !this.video.videoWidth) return;
    this.busy = true;
    const height = Math.round((WIDTH * this.video.videoHeight) / this.video.videoWidth);
    this.canvas.width = WIDTH;
    this.canvas.height = height;
    const capturedMs = this.frameCapturedMs ?? performance.now();
    this.canvas.getContext("2d").drawImage(this.video, 0, 0, WIDTH, height);
    this.canvas.toBlob(async (blob) => {
      try {
        if (blob && this.running) {
          this.send(new Uint8Array(await blob.arrayBuffer()), Math.max(0, capturedMs / 1000));
        }
      } finally {
        this.busy = false;
      }
    }, "image/jpeg", JPEG_QUALITY);
  }
}

/** The webcam status for a `tracked` answer: "tracking (face, hands)" or "no person found". */
export function trackedText(tracked) {
  if (!tracked.found) return "no person found: face the camera, in good light";
  const seen = Object.entries(tracked.seen ?? {}).filter(([, yes]) => yes).map(([group]) => group);
  const hands = seen.filter((g) => g.endsWith("_hand")).length;
  const parts = [seen.includes("face") && "face", hands && (hands === 2 ? "hands" : "one hand"),
    seen.includes("pose") && "body"].filter(Boolean);
  return parts.length ? `tracking (${parts.join(", ")})` : "tracking";
}
