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

// ---- drive -> frame latency over WebRTC: frame stamps (protocol/stamp.py) ------------------
// With `stamp=1` the server writes, into each frame's top-left strip, the seq of the newest
// drive that frame shows: 32 square cells (4 marker bits 1010, the 24-bit seq, 4 check bits),
// a 1 black, a 0 white, cells `width // 32` px (2 to 8). The page reads it from each presented
// frame and matches it with the drive it sent; the strip itself is clipped off the <video>.

export const STAMP = Object.freeze({ cells: 32, marker: [1, 0, 1, 0], seqBits: 24, minCell: 2, maxCell: 8 });

/** The stamp's cell side (px) in a frame `width` px wide; 0 when the frame is too narrow. */
export function stampCell(width) {
  const size = Math.min(STAMP.maxCell, Math.floor(width / STAMP.cells));
  return size < STAMP.minCell ? 0 : size;
}

function stampBits(seq) {
  const bits = [...STAMP.marker];
  for (let i = STAMP.seqBits - 1; i >= 0; i -= 1) bits.push(Math.floor(seq / 2 ** i) % 2);
  let sum = 0;
  for (let i = 0; i < STAMP.seqBits / 4; i += 1) sum += Math.floor(seq / 16 ** i) % 16;
  const check = ~sum & 0xF;  // inverted: a flat white or black strip never reads as a stamp
  for (let i = 3; i >= 0; i -= 1) bits.push((check >> i) & 1);
  return bits;
}

/** The seq in a stamp strip: `rgba` (ImageData.data) of `cell` x (32 * cell) px, as drawn
 *  from the frame's top-left corner; null when it holds no valid stamp. */
export function readStamp(rgba, cell) {
  const width = STAMP.cells * cell;
  const lo = Math.floor(cell / 4);
  const hi = cell - lo;  // each cell's centre: its edges bleed after a codec
  const bits = [];
  for (let c = 0; c < STAMP.cells; c += 1) {
    let sum = 0;
    let n = 0;
    for (let y = lo; y < hi; y += 1) {
      for (let x = c * cell + lo; x < c * cell + hi; x += 1) {
        const i = 4 * (y * width + x);
        sum += (rgba[i] + rgba[i + 1] + rgba[i + 2]) / 3;
        n += 1;
      }
    }
    bits.push(sum / n < 128 ? 1 : 0);
  }
  if (STAMP.marker.some((bit, i) => bits[i] !== bit)) return null;
  const seq = bits.slice(4, 4 + STAMP.seqBits).reduce((value, bit) => value * 2 + bit, 0);
  return stampBits(seq).every((bit, i) => bit === bits[i]) ? seq : null;
}

/** Read the stamp of every frame `video` presents: `onSeq(seq, presentedAt)` (performance.now
 *  clock) for each valid one. The strip is clipped off the picture. Returns a stop function;
 *  a no-op where the browser lacks requestVideoFrameCallback. */
export function watchStamps(video, onSeq) {
  if (!video.requestVideoFrameCallback) return () => {};
  const canvas = document.createElement("canvas");
  const ctx = canvas.getContext("2d", { willReadFrequently: true });
  let handle = null;
  const tick = (now, meta) => {
    const cell = stampCell(meta.width);
    if (cell) {
      // Twice the strip: the codec smears its edge into the rows below (seen at 512 px).
      video.style.clipPath = `inset(${(200 * cell) / meta.height}% 0 0 0)`;
      canvas.width = STAMP.cells * cell;
      canvas.height = cell;
      ctx.drawImage(video, 0, 0, canvas.width, cell, 0, 0, canvas.width, cell);
      const seq = readStamp(ctx.getImageData(0, 0, canvas.width, cell).data, cell);
      // 0xFFFFFF: a frame that shows no drive yet (seq -1)
      if (seq !== null && seq !== 0xFFFFFF) onSeq(seq, meta.presentationTime ?? now);
    }
    handle = video.requestVideoFrameCallback(tick);
  };
  handle = video.requestVideoFrameCallback(tick);
  return () => {
    video.cancelVideoFrameCallback?.(handle);
    video.style.clipPath = "";
  };
}
