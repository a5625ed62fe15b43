// Voices in a room over WebRTC (issue 30): a performer's microphone goes up on a sendonly Opus
// line of its WHEP offer; each seat's voice comes down on a recvonly line (the first line seat
// 0, the next seat 1, ...; the server answers lines past the room's seats inactive, and sends a
// performer no voice of its own seat). The voices are in the video's MediaStream on the
// server's side, so the browser lip-syncs them; each plays in its own <audio> with the
// viewer's own volume and mute. Who speaks: the inbound audio level (getStats), polled, and
// the mean level of what played since the last poll.
// WHEP has no renegotiation: turning the microphone on or off reconnects.

export const VOICE_LINES = 4;     // seats this page can hear (recvonly lines offered)
export const SPEAKING_LEVEL = 0.02;  // inbound-rtp audioLevel (0..1) above which a seat speaks

export function openMicrophone() {
  return navigator.mediaDevices.getUserMedia({ audio: true, video: false });
}

/** The RMS level (0..1) of what played since the last poll, from inbound-rtp's
 * totalAudioEnergy (level^2 x seconds, summed over every sample played) and
 * totalSamplesDuration; `previous`: {energy, duration} of the last poll. null without both, or
 * when no time passed. A 1 Hz poll of audioLevel alone reads one instant, and can keep missing
 * a voice that pulses at the poll's own period (Chromium's fake microphone beeps once a
 * second: a viewer then heard 3,000 packets and never "speaking"). */
export function intervalLevel(previous, energy, duration) {
  if (previous == null || energy == null || duration == null) return null;
  const seconds = duration - previous.duration;
  if (!(seconds > 0)) return null;
  return Math.sqrt(Math.max(0, energy - previous.energy) / seconds);
}

/** What a voice line is called: its seat, or the room's mix (a viewer's #voice-mix). */
export function voiceName(index, mixed = false) {
  return mixed ? "all seats (mix)" : `seat ${index}`;
}

/** "speaking: seat 0, seat 2" (or the mix) for the voices in `seats` (index -> {speaking}). */
export function speakingText(seats, mixed = false) {
  const names = [...seats].filter(([, s]) => s.speaking).map(([i]) => voiceName(i, mixed));
  return names.length ? `speaking: ${names.join(", ")}` : "";
}

/** A row in `panel` for seat `index`: its label (returned), a volume slider and a mute box
 *  calling `on.volume(0..1)` and `on.mute(bool)`; `extra`: an element to add (its <audio>);
 *  `mixed`: the line is the room's mix. */
export function seatControls(panel, index, on, extra = null, mixed = false) {
  const row = document.createElement("div");
  row.className = "voice";
  const volume = Object.assign(document.createElement("input"), {
    type: "range", min: "0", max: "1", step: "0.05", value: "1",
    title: `${voiceName(index, mixed)} volume`,
  });
  volume.addEventListener("input", () => on.volume(Number(volume.value)));
  const mute = Object.assign(document.createElement("input"), { type: "checkbox" });
  mute.addEventListener("change", () => on.mute(mute.checked));
  const label = document.createElement("span");
  label.textContent = voiceName(index, mixed);
  const muteLabel = document.createElement("label");
  muteLabel.append(mute, " mute");
  row.append(label, volume, muteLabel, ...(extra ? [extra] : []));
  panel.append(row);
  return label;
}

export class RoomVoices {
  /** `panel`: the element that lists the seats heard. */
  constructor(panel) {
    this.panel = panel;
    this.mic = null;        // MediaStream of the microphone, while performing with it
    this.micMuted = false;
    this.lines = [];        // recvonly transceivers, seat order
    this.seats = new Map(); // seat index -> {audio, receiver, speaking, level, played}
    this.mixed = false;     // asked for the room's mix: the first line carries it
  }

  /** Before the offer: the microphone (if any) and one recvonly line per seat. */
  attach(pc, mic = null) {
    this.stop();
    this.mic = mic;
    if (mic) {
      const [track] = mic.getAudioTracks();
      track.enabled = !this.micMuted;
      pc.addTransceiver(track, { direction: "sendonly", streams: [mic] });
    }
    this.lines = Array.from({ length: VOICE_LINES },
      () => pc.addTransceiver("audio", { direction: "recvonly" }));
    pc.addEventListener("track", (event) => {
      if (event.track.kind === "audio") this._heard(event);
    });
  }

  _heard(event) {
    const index = this.lines.findIndex((t) => t.receiver === event.receiver);
    if (index < 0) return;
    const audio = document.createElement("audio");
    audio.autoplay = true;
    audio.srcObject = new MediaStream([event.track]);
    const label = seatControls(this.panel, index, {
      volume: (v) => { audio.volume = v; },
      mute: (m) => { audio.muted = m; },
    }, audio, this.mixed);
    this.seats.set(index, { audio, receiver: event.receiver, label, speaking: false, level: 0,
                            played: null });
    audio.play().catch(() => { /* autoplay refused until a click: the page says so */ });
  }

  setMicMuted(muted) {
    this.micMuted = muted;
    for (const track of this.mic?.getAudioTracks() ?? []) track.enabled = !muted;
  }

  setSeatVolume(index, volume, muted = false) {
    const seat = this.seats.get(index);
    if (!seat) return false;
    seat.audio.volume = volume;
    seat.audio.muted = muted;
    return true;
  }

  /** Each seat's audio level and whether it speaks now; [{seat, level, speaking, ...}]. */
  async poll() {
    const out = [];
    for (const [index, seat] of this.seats) {
      let level = 0, packets = 0, energy = null, duration = null;
      try {
        (await seat.receiver.getStats()).forEach((s) => {
          if (s.type === "inbound-rtp" && s.kind === "audio") {
            level = s.audioLevel ?? 0;
            packets = s.packetsReceived ?? 0;
            energy = s.totalAudioEnergy ?? null;
            duration = s.totalSamplesDuration ?? null;
          }
        });
      } catch { /* closed meanwhile */ }
      level = Math.max(level, intervalLevel(seat.played, energy, duration) ?? 0);
      seat.played = energy == null || duration == null ? null : { energy, duration };
      seat.level = level;
      seat.speaking = level > SPEAKING_LEVEL;
      seat.label.textContent = `${voiceName(index, this.mixed)}${seat.speaking ? " (speaking)" : ""}`;
      out.push({ seat: index, level, packets, speaking: seat.speaking, mixed: this.mixed,
                 volume: seat.audio.volume, muted: seat.audio.muted });
    }
    return out;
  }

  /** Who speaks, for the presence line: "speaking: seat 0" or "". */
  speakingText() {
    return speakingText(this.seats, this.mixed);
  }

  stop() {
    for (const track of this.mic?.getTracks() ?? []) track.stop();
    this.mic = null;
    for (const seat of this.seats.values()) seat.audio.srcObject = null;
    this.seats.clear();
    this.panel.replaceChildren();
  }
}
