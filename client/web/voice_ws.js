// Voices over the WebSocket (issue 30), for pages without WebRTC: the performer's microphone
// is encoded to Opus with WebCodecs (AudioEncoder: 20 ms frames, 48 kHz mono) and sent as
// `voice` messages stamped with their capture time; a viewer decodes each seat's packets
// (AudioDecoder) and plays them in an AudioContext, each seat through its own gain (volume,
// mute). Capture times are seconds of performance.now() on the performer's page, the clock
// its drives' t_capture use; frames carry their drive's t_capture, so the viewer plays a
// sound captured at T when the picture of T shows: at T + the picture's delay.

import { seatControls, speakingText, voiceName } from "./voice.js";

export const SAMPLE_RATE = 48000;
export const FRAME_US = 20000;         // one Opus frame: 20 ms
export const VOICE_BITRATE = 32000;    // bits/s the page prefers; the server's welcome.voice
//                                        bounds lower it (voiceBitrate)
export const MIN_BITRATE = 6000;       // Opus' lowest (and the server's voice_max_bitrate's)
export const PACKET_HEADROOM = 2;      // a VBR packet may be this many times its average size
export const JITTER_MS = 40;           // ahead of the fastest packet: relay and network jitter
export const MAX_DELAY_MS = 500;       // the longest a voice waits for the picture (as the
//                                        server's WebRTC buffer once did): past it, lips lag
export const RESYNC_MS = 20;           // a drift of the target delay past this moves playback
export const LAG_SAMPLES = 15;         // picture lags the delay is the median of
export const AUDIO_LAG_PACKETS = 100;  // the fastest packet of the last 2 s sets the voice's lag
export const MAX_DECODE_QUEUE = 50;    // packets waiting for the decoder; past it dropped
export const REANCHOR_MS = 10;         // the mic's stamps follow its sample count until the
//                                        output clock mapping is this far off
export const SPEAKING_LEVEL = 0.02;    // decoded RMS (0..1) above which a seat speaks
const SYNC_LOG = 1000;                 // (capture, play) pairs kept for tests and the console

/** Why this browser cannot speak or hear over the WebSocket, or null when it can. */
export function voiceUnsupported() {
  if (typeof AudioEncoder !== "function" || typeof AudioDecoder !== "function") {
    return "this browser has no WebCodecs audio (AudioEncoder/AudioDecoder; needs https or localhost)";
  }
  if (typeof AudioWorkletNode !== "function") return "this browser has no AudioWorklet";
  return null;
}

/** RFC 6464's level of `samples` (floats, full scale 1): dBov, -127 (silence) .. 0. */
export function levelDbov(samples) {
  let sum = 0;
  for (const s of samples) sum += s * s;
  const rms = Math.sqrt(sum / Math.max(1, samples.length));
  return rms > 0 ? Math.max(-127, Math.min(0, 20 * Math.log10(rms))) : -127;
}

/** The bit rate to encode at: the page's preference, within the server's bounds (welcome.voice,
 *  protocol minor 4: max_bitrate, and max_packet_bytes with room for VBR's larger packets). */
export function voiceBitrate(bounds, preferred = VOICE_BITRATE) {
  let rate = preferred;
  if (bounds?.max_bitrate) rate = Math.min(rate, bounds.max_bitrate);
  if (bounds?.max_packet_bytes) {
    rate = Math.min(rate, (bounds.max_packet_bytes * 8 * 1e6) / FRAME_US / PACKET_HEADROOM);
  }
  return Math.max(MIN_BITRATE, Math.floor(rate));
}

function median(values) {
  const sorted = [...values].sort((a, b) => a - b);
  return sorted[Math.floor(sorted.length / 2)];
}

/** performance.now() (ms) <-> an AudioContext's time (s) of the sound heard at that instant. */
function contextTimeAt(ctx, perfMs) {
  const ts = ctx.getOutputTimestamp();
  if (!ts.performanceTime) return ctx.currentTime + (perfMs - performance.now()) / 1000;
  return ts.contextTime + (perfMs - ts.performanceTime) / 1000;
}

function perfTimeAt(ctx, contextTime) {
  const ts = ctx.getOutputTimestamp();
  if (!ts.performanceTime) return performance.now() + (contextTime - ctx.currentTime) * 1000;
  return ts.performanceTime + (contextTime - ts.contextTime) * 1000;
}

/** A performer's microphone as Opus packets: `send(bytes, tCaptureS, levelDbov)` each 20 ms. */
export class WsMicrophone {
  constructor(send) {
    this.send = send;
    this.stream = null;
    this.ctx = null;
    this.encoder = null;
    // Each frame sent to the encoder, in order: {capturedMs, level}. Packet k is frame k
    // (20 ms each), so it takes frame k's own stamp: the encoder's timestamps count samples
    // from the first frame on and would drift from performance.now() (measured: 10.6 ms
    // off from the second packet on in Chromium).
    this.frames = [];
    this.muted = false;
    this.sent = 0;
    this.errors = 0;
    this.oversized = 0;          // packets past the server's max_packet_bytes: not sent
    this.bitrate = null;         // what the encoder was set to
    this.maxPacketBytes = Infinity;
  }

  /** `bounds`: the welcome's voice bounds (null from a server before protocol minor 4). */
  async start(stream, bounds = null) {
    const bitrate = voiceBitrate(bounds);
    this.bitrate = bitrate;
    this.maxPacketBytes = bounds?.max_packet_bytes ?? Infinity;
    const config = {
      codec: "opus", sampleRate: SAMPLE_RATE, numberOfChannels: 1, bitrate,
      opus: { frameDuration: FRAME_US },
    };
    if (!(await AudioEncoder.isConfigSupported(config)).supported) {
      throw new Error("this browser cannot encode Opus (AudioEncoder)");
    }
    this.stream = stream;
    this.setMuted(this.muted);
    this.encoder = new AudioEncoder({
      output: (chunk) => this._packet(chunk),
      error: () => { this.errors += 1; },
    });
    this.encoder.configure(config);
    this.ctx = new AudioContext({ sampleRate: SAMPLE_RATE });
    await this.ctx.audioWorklet.addModule(new URL("./mic_worklet.js", import.meta.url));
    const frames = new AudioWorkletNode(this.ctx, "mic-frames", {
      numberOfInputs: 1, numberOfOutputs: 1, channelCount: 1, channelCountMode: "explicit",
    });
    frames.port.onmessage = (event) => this._frame(event.data);
    const silent = this.ctx.createGain();  // pulls the worklet; nothing reaches the speakers
    silent.gain.value = 0;
    this.ctx.createMediaStreamSource(stream).connect(frames).connect(silent)
      .connect(this.ctx.destination);
    await this.ctx.resume();
  }

  /** Capture time (ms, performance.now()) of the context frame `frame`: the instant it would
   *  be heard, less the output's latencies (it is processed that much earlier) and the
   *  input's (it was captured that much before). */
  _capturedMs(frame) {
    const track = this.stream.getAudioTracks()[0];
    const inputS = track?.getSettings().latency ?? 0;
    const aheadS = (this.ctx.baseLatency ?? 0) + (this.ctx.outputLatency ?? 0) + inputS;
    const live = perfTimeAt(this.ctx, frame / SAMPLE_RATE) - aheadS * 1000;
    // The mapping jitters by ms; counting samples from an anchor keeps packets 20 ms apart.
    const counted = this.anchor && this.anchor.ms + (frame - this.anchor.frame) / SAMPLE_RATE * 1000;
    if (!this.anchor || Math.abs(live - counted) > REANCHOR_MS) {
      this.anchor = { frame, ms: live };
      return live;
    }
    return counted;
  }

  _frame({ samples, frame }) {
    if (this.encoder?.state !== "configured") return;
    const capturedMs = Math.max(0, this._capturedMs(frame));
    this.frames.push({ capturedMs, level: levelDbov(samples) });
    const data = new AudioData({
      format: "f32-planar", sampleRate: SAMPLE_RATE, numberOfFrames: samples.length,
      numberOfChannels: 1, timestamp: Math.round(capturedMs * 1000), data: samples,
    });
    this.encoder.encode(data);
    data.close();
  }

  _packet(chunk) {
    const bytes = new Uint8Array(chunk.byteLength);
    chunk.copyTo(bytes);
    const frame = this.frames.shift();
    const capturedMs = frame?.capturedMs ?? chunk.timestamp / 1000;
    if (bytes.length > this.maxPacketBytes) {  // the server would drop it: not sent
      this.oversized += 1;
      return;
    }
    this.sent += 1;
    this.send(bytes, Math.max(0, capturedMs / 1000), this.muted ? -127 : frame?.level ?? -127);
  }

  /** Muted: the track gives silence, still sent (as WebRTC does): nobody hears, nobody speaks. */
  setMuted(muted) {
    this.muted = muted;
    for (const track of this.stream?.getAudioTracks() ?? []) track.enabled = !muted;
  }

  stop() {
    for (const track of this.stream?.getTracks() ?? []) track.stop();
    if (this.encoder?.state === "configured") this.encoder.close();
    this.ctx?.close();
    this.stream = this.ctx = this.encoder = null;
    this.frames = [];
    this.anchor = null;  // {frame, ms}: a context frame and its capture time
  }
}

/** A viewer's voices: each seat's `voice` messages decoded and played in step with the picture. */
export class WsVoices {
  /** `panel`: the element listing the seats heard; `pictureSeat`: the seat whose drives'
   *  t_capture the frames carry (the one performed, else the one followed: 0). */
  constructor(panel, pictureSeat = 0) {
    this.panel = panel;
    this.pictureSeat = pictureSeat;
    this.ctx = null;
    this.seats = new Map();
    this.pictureLags = [];        // ms: shown - t_capture of each drive's first frame shown
    this.lastPicture = null;      // the t_capture of the last frame that measured
    this.log = { packets: [], frames: [] };  // [seat, t_capture s, played at ms] / [t_capture s, shown at ms]
    this.mixed = false;           // asked for the room's mix: its packets come without a seat
  }

  /** A frame was drawn at `shownMs` (performance.now()); it showed the drive of `tCapture`. */
  picture(tCapture, shownMs) {
    if (tCapture == null || tCapture === this.lastPicture) return;  // the first frame of each
    this.lastPicture = tCapture;
    this.pictureLags.push(shownMs - tCapture * 1000);
    if (this.pictureLags.length > LAG_SAMPLES) this.pictureLags.shift();
    this._remember(this.log.frames, [tCapture, shownMs]);
  }

  _remember(list, entry) {
    list.push(entry);
    if (list.length > SYNC_LOG) list.shift();
  }

  /** How much later than its fastest packets the picture shows the same instant (ms), or
   *  null before both are known (frames and the voice are on the same performer's clock). */
  pictureExtraMs() {
    // the mix (seat 0 here) is stamped on the picture seat's clock by the server
    const seat = this.seats.get(this.mixed ? 0 : this.pictureSeat);
    if (!this.pictureLags.length || !seat?.audioLags.length) return null;
    return median(this.pictureLags) - Math.min(...seat.audioLags);
  }

  _seat(index) {
    let seat = this.seats.get(index);
    if (seat) return seat;
    this.ctx ??= new AudioContext({ sampleRate: SAMPLE_RATE });
    const gain = this.ctx.createGain();
    gain.connect(this.ctx.destination);
    seat = {
      gain, decoder: null, pending: new Map(), audioLags: [], offsetMs: null, nextStart: 0,
      packets: 0, decoded: 0, played: 0, late: 0, dropped: 0, errors: 0, level: 0, peak: 0,
      volume: 1, muted: false, speaking: false,
    };
    seat.label = seatControls(this.panel, index, {
      volume: (v) => this.setSeatVolume(index, v, seat.muted),
      mute: (m) => this.setSeatVolume(index, seat.volume, m),
    }, null, this.mixed);
    this.seats.set(index, seat);
    return seat;
  }

  _decoder(index, seat) {
    if (seat.decoder?.state === "configured") return seat.decoder;
    seat.pending.clear();
    seat.decoder = new AudioDecoder({
      output: (data) => this._decoded(index, seat, data),
      error: () => { seat.errors += 1; },  // closed: the next packet makes a new one
    });
    seat.decoder.configure({ codec: "opus", sampleRate: SAMPLE_RATE, numberOfChannels: 1 });
    return seat.decoder;
  }

  /** A `voice` message from the server. */
  packet(message) {
    const index = message.seat ?? 0;
    const seat = this._seat(index);
    const arrivedMs = performance.now();
    seat.packets += 1;
    if (message.t_capture != null) {
      seat.audioLags.push(arrivedMs - message.t_capture * 1000);
      if (seat.audioLags.length > AUDIO_LAG_PACKETS) seat.audioLags.shift();
    }
    const decoder = this._decoder(index, seat);
    if (decoder.decodeQueueSize > MAX_DECODE_QUEUE) {
      seat.dropped += 1;
      return;
    }
    const timestamp = message.seq * FRAME_US;  // unique per packet: finds it again on output
    seat.pending.set(timestamp, { tCapture: message.t_capture ?? null, arrivedMs });
    decoder.decode(new EncodedAudioChunk({ type: "key", timestamp, data: message.data }));
  }

  /** When a packet is to be heard (ms): its capture time plus the seat's delay, which is its
   *  fastest packets' lag plus the picture's extra delay (at least JITTER_MS, at most
   *  MAX_DELAY_MS); the delay moves only when its target drifts past RESYNC_MS. */
  _playAtMs(seat, meta) {
    if (meta.tCapture == null || !seat.audioLags.length) return meta.arrivedMs + JITTER_MS;
    const extra = Math.min(MAX_DELAY_MS, Math.max(JITTER_MS, this.pictureExtraMs() ?? JITTER_MS));
    const target = Math.min(...seat.audioLags) + extra;
    if (seat.offsetMs === null || Math.abs(target - seat.offsetMs) > RESYNC_MS) {
      seat.offsetMs = target;
    }
    const at = meta.tCapture * 1000 + seat.offsetMs;
    return Math.min(at, meta.arrivedMs + MAX_DELAY_MS);  // the buffer is bounded
  }

  _decoded(index, seat, data) {
    const meta = seat.pending.get(data.timestamp);
    seat.pending.delete(data.timestamp);
    const frames = data.numberOfFrames;
    const buffer = this.ctx.createBuffer(1, frames, data.sampleRate);
    const samples = new Float32Array(frames);
    data.copyTo(samples, { planeIndex: 0, format: "f32-planar" });
    data.close();
    buffer.copyToChannel(samples, 0);
    seat.decoded += 1;
    let sum = 0, peak = 0;
    for (const s of samples) { sum += s * s; peak = Math.max(peak, Math.abs(s)); }
    seat.level = Math.max(seat.level, Math.sqrt(sum / frames));
    seat.peak = Math.max(seat.peak, peak);
    if (!meta) return;
    let start = contextTimeAt(this.ctx, this._playAtMs(seat, meta));
    // Back to back with the previous packet when within a few ms: no clicks from jitter.
    if (Math.abs(start - seat.nextStart) < RESYNC_MS / 2000) start = seat.nextStart;
    const now = this.ctx.currentTime;
    if (start < now) {
      seat.late += 1;
      if (now - start > FRAME_US / 1e6) return;  // more than a frame late: dropped
      start = now;
    }
    const source = this.ctx.createBufferSource();
    source.buffer = buffer;
    source.connect(seat.gain);
    source.start(start);
    seat.nextStart = start + buffer.duration;
    seat.played += 1;
    this._remember(this.log.packets, [index, meta.tCapture, perfTimeAt(this.ctx, start)]);
  }

  setSeatVolume(index, volume, muted = false) {
    const seat = this.seats.get(index);
    if (!seat) return false;
    seat.volume = volume;
    seat.muted = muted;
    seat.gain.gain.value = muted ? 0 : volume;
    return true;
  }

  /** Each seat's figures since the last poll; [{seat, level, speaking, packets, ...}]. */
  poll() {
    const out = [];
    for (const [index, seat] of this.seats) {
      seat.speaking = seat.level > SPEAKING_LEVEL;
      seat.label.textContent = `${voiceName(index, this.mixed)}${seat.speaking ? " (speaking)" : ""}`;
      const { packets, decoded, played, late, dropped, errors, level, peak, volume, muted,
              speaking, offsetMs } = seat;
      out.push({ seat: index, packets, decoded, played, late, dropped, errors, level, peak,
                 volume, muted, speaking, delayMs: offsetMs, state: this.ctx?.state,
                 mixed: this.mixed });
      seat.level = 0;
    }
    return out;
  }

  speakingText() {
    return speakingText(this.seats, this.mixed);
  }

  /** A page may not start audio before a click: resume then. */
  resume() {
    if (this.ctx?.state === "suspended") this.ctx.resume();
  }

  stop() {
    for (const seat of this.seats.values()) {
      if (seat.decoder?.state === "configured") seat.decoder.close();
    }
    this.seats.clear();
    this.ctx?.close();
    this.ctx = null;
    this.panel.replaceChildren();
  }
}
