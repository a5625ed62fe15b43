// The Telesplat page: pick an avatar, watch its live stream, orbit, drive it with clips,
// sliders or the webcam. The token comes from the address (#token=, as the server prints it,
// or ?token= from older links); it is moved into memory and removed from the address bar at
// once, then travels only in the WebSocket's hello and REST calls' Authorization header.

import { Controls } from "./controls.js";
import { MotionPlayer } from "./motions.js";
import { OrbitControl } from "./orbit.js";
import { Session, streamUrl, takeToken } from "./session.js";
import { StreamStats, renderStats } from "./stats.js";
import { Webcam } from "./webcam.js";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const token = takeToken(window);

// Shared with tests and the console: what the page is doing.
const state = window.telesplat = {
  session: null, stats: new StreamStats(), framesShown: 0, errors: [], avatar: null,
};

function notify(text, kind = "info") {
  const line = document.createElement("div");
  line.className = `note ${kind}`;
  line.textContent = `${new Date().toLocaleTimeString()}  ${text}`;
  $("messages").prepend(line);
  while ($("messages").childElementCount > 8) $("messages").lastElementChild.remove();
}

async function api(path) {
  const response = await fetch(path, { headers: token ? { Authorization: `Bearer ${token}` } : {} });
  if (!response.ok) {
    let detail = response.statusText;
    try { detail = (await response.json()).detail ?? detail; } catch { /* not JSON */ }
    const error = new Error(`${response.status} ${typeof detail === "string" ? detail : JSON.stringify(detail)}`);
    error.status = response.status;
    throw error;
  }
  return response.json();
}

// ---- frames on the canvas: the newest wins, decodes never queue up ---------------------

const canvas = $("view");
const ctx = canvas.getContext("2d");
let pending = null;
let decoding = false;

async function drawPending() {
  decoding = true;
  try {
    while (pending) {  // each pass takes the newest frame; ends when none came meanwhile
      const frame = pending;
      pending = null;
      const type = frame.codec === "png" ? "image/png" : "image/jpeg";
      const bitmap = await createImageBitmap(new Blob([frame.data], { type }));
      if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
        canvas.width = bitmap.width;
        canvas.height = bitmap.height;
      }
      ctx.drawImage(bitmap, 0, 0);
      bitmap.close();
      state.framesShown += 1;
    }
  } catch (err) {
    notify(`could not show a frame: ${err}`, "error");
  } finally {
    decoding = false;
  }
}

function showFrame(frame) {
  state.stats.frame(frame);
  if (frame.codec === "h264") return;  // the page asks for JPEG; never decodes video
  pending = frame;
  if (!decoding) drawPending();
}

// ---- the session ------------------------------------------------------------------------

const controls = new Controls($("sliders"), (families) => drive(families));
const player = new MotionPlayer(api, (families, reset) => drive(families, reset));
const orbit = new OrbitControl(canvas, (view, moving) => state.session?.view(view, moving));
const webcam = new Webcam((bytes) => state.session?.image(bytes));
state.orbit = orbit;
state.player = player;

function drive(families, reset = false) {
  try {
    state.session?.drive(families, reset);
  } catch (err) {
    notify(String(err.message || err), "error");
  }
}

function sendRequest() {
  const size = Number($("size").value);
  state.session?.request({ width: size, height: size, codec: "jpeg" });
}

function onServerError(message) {
  state.errors.push(message);
  const about = message.answers?.type ? ` (answering ${message.answers.type})` : "";
  if (message.answers?.type === "image") {
    $("webcam-status").textContent = `server: ${message.code}: ${message.message}`;
  }
  notify(`server error ${message.code}${about}: ${message.message}`, "error");
}

async function connect(avatarId) {
  state.session?.close();
  player.stop();
  state.avatar = avatarId;
  $("status").textContent = `connecting to ${avatarId}…`;
  const session = new Session(streamUrl(avatarId), token);
  state.session = session;
  session.addEventListener("frame", (e) => showFrame(e.detail));
  session.addEventListener("servererror", (e) => onServerError(e.detail));
  session.addEventListener("stats", (e) => { state.stats.server = e.detail; });
  session.addEventListener("pong", (e) => { state.stats.rttMs = e.detail.rttMs; });
  session.addEventListener("close", (e) => {
    if (state.session === session) $("status").textContent = `disconnected (${e.detail.code}) ${e.detail.reason}`;
  });
  try {
    const welcome = await session.ready;
    const info = welcome.avatar;
    $("status").textContent = `${info.name} — ${info.num_gaussians} Gaussians, session ${welcome.session}`;
    controls.build(info.metadata?.expression_names || []);
    sendRequest();
    session.view({ ...orbit.orbit }, false);
    session.ping();
  } catch (err) {
    $("status").textContent = `could not connect: ${err.code ? `${err.code}: ` : ""}${err.message}`;
  }
}

// ---- panels -----------------------------------------------------------------------------

async function loadAvatars() {
  const select = $("avatar");
  let avatars;
  try {
    const body = await api("/v1/avatars");
    avatars = Array.isArray(body) ? body : body.avatars;
  } catch (err) {
    $("status").textContent = `cannot list avatars: ${err.message}`;
    return;
  }
  select.replaceChildren(...avatars.map((a) => new Option(`${a.name || a.id} (${a.id})`, a.id)));
  if (!avatars.length) {
    $("status").textContent = "no avatars on this server yet";
    return;
  }
  const wanted = params.get("avatar");
  select.value = avatars.some((a) => a.id === wanted) ? wanted : avatars[0].id;
  await connect(select.value);
}

async function loadMotions() {
  let motions;
  try {
    motions = await player.list();
  } catch (err) {
    $("motions").textContent = err.status === 404
      ? "this server does not offer motion clips" : `motion clips unavailable: ${err.message}`;
    return;
  }
  const groups = new Map();
  for (const m of motions) {
    const name = typeof m === "string" ? m : m.name;
    const category = (typeof m === "object" && m.category) || "motions";
    if (!groups.has(category)) groups.set(category, []);
    groups.get(category).push(name);
  }
  $("motions").replaceChildren(...[...groups].map(([category, names]) => {
    const box = document.createElement("fieldset");
    box.append(Object.assign(document.createElement("legend"), { textContent: category }));
    for (const name of names) {
      const button = Object.assign(document.createElement("button"), { textContent: name });
      button.dataset.motion = name;
      button.addEventListener("click", () => player.play(name, state.avatar)
        .catch((err) => notify(`cannot play ${name}: ${err.message}`, "error")));
      box.append(button);
    }
    return box;
  }));
}

function wire() {
  $("avatar").addEventListener("change", (e) => connect(e.target.value));
  $("size").addEventListener("change", sendRequest);
  $("reset").addEventListener("click", () => {
    player.stop();
    controls.reset();
    drive({}, true);
  });
  $("stop").addEventListener("click", () => player.stop());
  $("loop").addEventListener("change", (e) => { player.loop = e.target.checked; });
  player.onState = (p) => { $("playing").textContent = p ? `playing ${p.name}` : ""; };
  $("webcam").addEventListener("change", async (e) => {
    if (!e.target.checked) {
      webcam.stop();
      $("webcam-status").textContent = "off";
      return;
    }
    try {
      await webcam.start();
      $("webcam-status").textContent = "sending frames…";
    } catch (err) {
      e.target.checked = false;
      $("webcam-status").textContent = `camera unavailable: ${err.message}`;
    }
  });
  setInterval(() => renderStats($("stats"), state.stats.summary()), 250);
  setInterval(() => state.session?.ping(), 1000);
}

wire();
if (!token) notify("no #token= in the address: the server prints a URL with one", "error");
loadAvatars();
loadMotions();
