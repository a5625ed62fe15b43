// The bar under the picture: reset view, fullscreen, snapshot, record, background colour, and
// the download links of what was saved. `page` gives what it acts on: {view (ViewControl),
// capture (Capture), sendBackground([r, g, b]), notify(text, kind)}.

import { hexToRgb, showSaved } from "./capture.js";

const $ = (id) => document.getElementById(id);

/** "#rrggbb" of a protocol background [r, g, b] in [0, 1]. */
export function rgbToHex(rgb) {
  return `#${rgb.map((c) => Math.round(c * 255).toString(16).padStart(2, "0")).join("")}`;
}

export function wireViewBar({ view, capture, sendBackground, notify }) {
  const fail = (what) => (err) => notify(`${what}: ${err.message || err}`, "error");
  $("reset-view").addEventListener("click", () => view.reset());
  $("fullscreen").addEventListener("click", () => capture.toggleFullscreen()
    .catch(fail("fullscreen refused")));
  document.addEventListener("fullscreenchange", () => {
    $("fullscreen").textContent = capture.fullscreen ? "Exit fullscreen" : "Fullscreen";
  });
  $("snapshot").addEventListener("click", () => capture.snapshot()
    .then((saved) => showSaved($("saved"), saved).click())  // the PNG downloads at once
    .catch(fail("no snapshot")));
  capture.onRecording = (on) => {
    $("record").textContent = on ? "Stop recording" : "Record";
    $("record").classList.toggle("recording", on);
  };
  $("record").addEventListener("click", () => {
    if (capture.recording) {
      capture.stop();
      return;
    }
    try {
      capture.record().then((saved) => showSaved($("saved"), saved), fail("recording failed"));
    } catch (err) {
      fail("cannot record")(err);
    }
  });
  $("record").title = `record up to ${capture.maxSeconds} s as WebM`;
  $("background").addEventListener("input", (e) => {
    $("background").dataset.chosen = "true";
    sendBackground(hexToRgb(e.target.value));
  });
}

/** The background the user chose (null: none yet, the server's default stays). */
export function chosenBackground() {
  const input = $("background");
  return input.dataset.chosen ? hexToRgb(input.value) : null;
}

/** Show the server's background (the welcome's request) until the user picks one. */
export function showBackground(rgb) {
  if (rgb && !$("background").dataset.chosen) $("background").value = rgbToHex(rgb);
}
