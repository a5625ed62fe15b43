// What the overlay shows of a WebRTC peer: one sample from RTCPeerConnection.getStats() (the
// received video's inbound-rtp, its codec, the selected candidate pair) and the rates between
// two samples. Pure functions over the report, so node can test them without a browser.

/** One sample from a getStats() report (a Map-like of id -> stats); null without video yet. */
export function rtcSample(report) {
  const byId = new Map();
  report.forEach((entry, id) => byId.set(id, entry));
  let inbound = null;
  let pair = null;
  let selectedPairId = null;
  for (const entry of byId.values()) {
    if (entry.type === "inbound-rtp" && (entry.kind ?? entry.mediaType) === "video") inbound = entry;
    if (entry.type === "transport" && entry.selectedCandidatePairId) {
      selectedPairId = entry.selectedCandidatePairId;
    }
  }
  if (selectedPairId) pair = byId.get(selectedPairId) ?? null;
  if (!pair) {  // older browsers: the nominated, succeeded pair
    for (const entry of byId.values()) {
      if (entry.type === "candidate-pair" && entry.nominated && entry.state === "succeeded") {
        pair = entry;
      }
    }
  }
  if (!inbound) return null;
  const codec = inbound.codecId ? byId.get(inbound.codecId) : null;
  return {
    t: inbound.timestamp,  // ms
    bytesReceived: inbound.bytesReceived ?? 0,
    framesDecoded: inbound.framesDecoded ?? 0,
    framesDropped: inbound.framesDropped ?? 0,
    jitterMs: inbound.jitter == null ? null : inbound.jitter * 1000,
    rttMs: pair?.currentRoundTripTime == null ? null : pair.currentRoundTripTime * 1000,
    codec: codec?.mimeType ? codec.mimeType.replace(/^video\//, "") : null,
    width: inbound.frameWidth ?? null,
    height: inbound.frameHeight ?? null,
  };
}

/** The overlay's WebRTC figures: bit rate and decode rate between `previous` and `current`
 *  samples (null rates until there are two), the counters and delays of `current`. */
export function rtcSummary(previous, current) {
  if (!current) return null;
  const seconds = previous ? (current.t - previous.t) / 1000 : 0;
  const rate = (key) => (seconds > 0 ? Math.max(0, current[key] - previous[key]) / seconds : null);
  const bytesPerS = rate("bytesReceived");
  return {
    bitrateKbps: bytesPerS == null ? null : (8 * bytesPerS) / 1000,
    fps: rate("framesDecoded"),
    framesDecoded: current.framesDecoded,
    framesDropped: current.framesDropped,
    jitterMs: current.jitterMs,
    rttMs: current.rttMs,
    codec: current.codec,
    size: current.width && current.height ? `${current.width}x${current.height}` : null,
  };
}
