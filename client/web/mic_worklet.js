// The microphone in 20 ms frames for the WebSocket voice (voice_ws.js): the audio thread
// gathers 960 mono samples (48 kHz) and posts them with the context frame of their first
// sample, so the page can stamp each frame with its capture time.

const FRAME = 960;  // one Opus frame of 20 ms at 48 kHz

class MicFrames extends AudioWorkletProcessor {
  constructor() {
    super();
    this.buffer = new Float32Array(FRAME);
    this.filled = 0;
    this.first = 0;  // context frame of buffer[0]
  }

  process(inputs) {
    const channel = inputs[0]?.[0];
    if (!channel) return true;  // no input yet
    let offset = 0;
    while (offset < channel.length) {
      if (this.filled === 0) this.first = currentFrame + offset;
      const take = Math.min(FRAME - this.filled, channel.length - offset);
      this.buffer.set(channel.subarray(offset, offset + take), this.filled);
      this.filled += take;
      offset += take;
      if (this.filled === FRAME) {
        this.port.postMessage({ samples: this.buffer, frame: this.first }, [this.buffer.buffer]);
        this.buffer = new Float32Array(FRAME);
        this.filled = 0;
      }
    }
    return true;
  }
}

registerProcessor("mic-frames", MicFrames);
