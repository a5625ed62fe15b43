// Lip sync past the browser's own (issue 30). A browser plays a WebRTC stream's voice and
// picture in sync by their sender reports, but leaves a difference under 30 ms alone (WebRTC's
// StreamSynchronization, kMinDeltaMs), and here the voice arrives 20-30 ms before the picture
// (the render). Chromium left the voice 27-41 ms behind the picture on this page; holding the
// picture at least PICTURE_HOLD_MS (the video receiver's jitterBufferTarget) brought it to
// -3..+12 ms in 7 of 8 runs, the picture shown 22-27 ms later (docs/benchmarks.md, "Lip sync
// past Chromium's own"). A controller on the browser's playout estimates
// (estimatedPlayoutTimestamp) was measured too and chased Chromium's sync instead of
// settling: the hold is fixed.
// It applies only while a voice is heard, so a silent room's picture is not held. Off with
// `?lipsync=0`.

export const PICTURE_HOLD_MS = 60;  // the picture's least jitter-buffer delay while a voice plays
export const RELEASE_POLLS = 5;     // polls without new voice packets before the hold goes

/** Packets received on every voice line of a getStats() report, summed; null: no voice line. */
export function voicePackets(report) {
  let total = null;
  report.forEach((s) => {
    if (s.type !== "inbound-rtp" || s.kind !== "audio") return;
    total = (total ?? 0) + (s.packetsReceived ?? 0);
  });
  return total;
}

/** The hold (ms) after a poll: `hold` now, `heard` whether new voice packets came since the
 *  last poll, `quiet` polls without any so far (this one counted). */
export function nextHold(hold, heard, quiet) {
  if (heard) return PICTURE_HOLD_MS;
  return quiet >= RELEASE_POLLS ? 0 : hold;
}

/** One peer's hold: `update(report)` with each getStats() report (the page polls once a
 *  second). `hold`: the picture's least delay now (ms). */
export class LipSync {
  constructor(pc) {
    this.pc = pc;
    this.hold = 0;
    this.quiet = 0;
    this._packets = 0;
  }

  update(report) {
    const packets = voicePackets(report) ?? 0;
    const heard = packets > this._packets;
    this._packets = packets;
    this.quiet = heard ? 0 : this.quiet + 1;
    this._apply(nextHold(this.hold, heard, this.quiet));
    return this.hold;
  }

  _apply(hold) {
    if (hold === this.hold) return;
    const receiver = this.pc.getReceivers().find((r) => r.track?.kind === "video");
    if (!receiver || !("jitterBufferTarget" in receiver)) return;  // not in this browser
    receiver.jitterBufferTarget = hold;
    this.hold = hold;
  }
}
