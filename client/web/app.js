// The Telesplat page: pick an avatar, watch its live stream, orbit, drive it with clips,
// sliders or the webcam. The token comes from the address (#token=, as the server prints it,
// or ?token= from older links); it is moved into memory and removed from the address bar at
// once, then travels only in the WebSocket's hello and REST calls' Authorization header.
// Opened at /?room=ID#token=T (an invitation link) it joins the room: as a viewer the drive
// controls are hidden (orbit and zoom stay), as a performer they drive the room's seat.
// Transport: WebRTC (webrtc.js: WHEP, a <video>, messages on a data channel) when the browser
// and the server both can, else the WebSocket (session.js); ?transport=ws forces the latter.
// Over WebRTC a solo page makes itself a private room and performs its seat 0.
// When the server restarts (error `restarting`, close 1012) or the connection drops (1006,
// 1001) the page reconnects by itself into the same room, role and seat (reconnect.js: backoff
// 0.25 s -> 4 s, jittered, `?reconnect=N` tries); a room that is gone stops it.

import { Controls } from "./controls.js";
import { Capture, recordSeconds } from "./capture.js";
import { MotionPlayer } from "./motions.js";
import { backoffDelay, reconnectDecision, reconnectPolicy, stopReason } from "./reconnect.js";
import { Session, streamUrl, takeToken } from "./session.js";
import {
  canShare, chosenName, inviteAll, presenceNote, presenceText, showLinks, statusLine, storeName,
} from "./share.js";
import { demoBanner, watchDemoBuild } from "./demo_build.js";
import { Enrollment, enrollConfig, enrollSeconds } from "./enroll.js";
import { StreamStats, overlayToggle, renderStats } from "./stats.js";
import { askForToken, unauthorized } from "./token.js";
import { ViewControl, fitToViewport } from "./view.js";
import { chosenBackground, showBackground, wireViewBar } from "./viewbar.js";
import { Webcam, trackedText } from "./webcam.js";
import { RoomVoices, openMicrophone } from "./voice.js";
import { WsMicrophone, WsVoices, voiceUnsupported } from "./voice_ws.js";
import {
  WhepSession, chooseTransport, deleteRoom, onVideoFrame, serverHealth, worthFallingBack,
} from "./webrtc.js";

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const token = takeToken(window);
const reconnect = reconnectPolicy(location.search);
let myName = chosenName(location.search);

// Shared with tests and the console: what the page is doing.
const state = window.telesplat = {
  session: null, stats: new StreamStats(), framesShown: 0, errors: [], avatar: null,
  room: null, presence: null, shareLinks: [],
  transport: null, transportWhy: null, privateRoom: null,  // privateRoom: the solo page's room id
  reconnecting: false, reconnects: 0, lastReconnect: null,  // {reason, downMs, attempts}
  demoBuild: null,  // the last /v1/demo status
  tracked: null,  // the last `tracked` answer to a webcam image
};

/** A refused token: say so and offer the token field (token.js). */
function tokenRefused(why) {
  askForToken($("token-form"), token ? `the server refused this token: ${why}`
    : `this server needs a token: ${why}`);
}

function notify(text, kind = "info") {
  const line = document.createElement("div");
  line.className = `note ${kind}`;
  line.textContent = `${new Date().toLocaleTimeString()}  ${text}`;
  $("messages").prepend(line);
  while ($("messages").childElementCount > 8) $("messages").lastElementChild.remove();
}

async function api(path, { method = "GET", body } = {}) {
  const headers = token ? { Authorization: `Bearer ${token}` } : {};
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const response = await fetch(path, {
    method, headers, body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (!response.ok) {
    let detail = response.statusText;
    try { detail = (await response.json()).detail ?? detail; } catch { /* not JSON */ }
    const error = new Error(`${response.status} ${typeof detail === "string" ? detail : JSON.stringify(detail)}`);
    error.status = response.status;
    throw error;
  }
  return response.status === 204 ? null : response.json();
}

// ---- frames on the canvas: the newest wins, decodes never queue up ---------------------

const canvas = $("view");
const video = $("video");
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
      state.frameCapture = frame.t_capture ?? null;  // its drive's (or webcam image's) capture
      wsVoices.picture(frame.t_capture, performance.now());  // the picture's delay, for the voice
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
// On the canvas and the video alike (view.js: orbit, zoom toward the face, pan, reset).
const orbit = new ViewControl([canvas, video], (view, moving) => {
  state.stats.input();
  state.session?.view(view, moving);
});
const capture = new Capture($("stage"), () => (canvas.hidden ? video : canvas),
  { maxSeconds: recordSeconds(location.search, (why) => notify(why, "error")) });
state.capture = capture;
state.saved = [];  // what snapshots and recordings saved: {kind, blob, url, name, size, ...}
capture.onSaved = (saved) => state.saved.push(saved);
const webcam = new Webcam((bytes, tCapture) => {
  state.stats.input();
  state.session?.image(bytes, "jpeg", tCapture);
});
const voices = new RoomVoices($("voices"));
const wsVoices = new WsVoices($("voices"));  // the WebSocket's voices (voice_ws.js)
let wsMic = null;  // the WebSocket performer's microphone, while on
state.wsVoices = wsVoices;
const enrollment = new Enrollment({
  guide: $("enroll-guide"), steps: $("enroll-steps"), length: $("enroll-length"),
  preview: $("enroll-preview"), status: $("enroll-status"), progress: $("enroll-progress"),
}, token, {
  seconds: enrollSeconds(location.search, (why) => notify(why, "error")),
  config: enrollConfig(location.search, (why) => notify(why, "error")),
});
state.enrollment = enrollment;  // its recording: enrollment.blob
state.enroll = enrollment.state;  // phase, seconds, bytes, step, jobId, events, avatarId, error
state.voices = [];  // the seats heard: [{seat, level, packets, speaking, volume, muted}]
state.orbit = orbit;
state.player = player;

function drive(families, reset = false) {
  state.stats.input();
  try {
    state.session?.drive(families, reset);
  } catch (err) {
    notify(String(err.message || err), "error");
  }
}

function sendRequest() {
  const size = Number($("size").value);
  const background = chosenBackground();
  state.session?.request({ width: size, height: size, codec: "jpeg",
    ...(background ? { background } : {}) });
}

function onServerError(message) {
  state.errors.push(message);
  const about = message.answers?.type ? ` (answering ${message.answers.type})` : "";
  if (message.answers?.type === "image") {
    $("webcam-status").textContent = `server: ${message.code}: ${message.message}`;
  }
  notify(`server error ${message.code}${about}: ${message.message}`, "error");
}

// Viewers keep orbit and zoom only; performers (and plain sessions) keep every control.
function setViewer(viewer) {
  $("drive-controls").hidden = viewer;
  $("viewer-note").hidden = !viewer;
  if (viewer) {
    player.stop();
    webcam.stop();
    enrollment.stop();
    $("webcam").checked = false;
  }
}

function showPresence(presence) {
  state.presence = presence;
  $("presence").textContent = presenceText(presence);
  const note = presenceNote(presence);
  if (note) notify(note);
}

/** Over WebRTC a performer speaks with the microphone when #mic is ticked (?mic=1). */
async function voiceMedia(target) {
  const performs = typeof target === "string" || target.role !== "watch";
  let mic = null;
  if (performs && $("mic").checked) {
    try {
      mic = await openMicrophone();
      $("mic-status").textContent = "speaking";
    } catch (err) {
      $("mic").checked = false;
      $("mic-status").textContent = `microphone unavailable: ${err.message}`;
    }
  }
  return (pc) => voices.attach(pc, mic);
}

/** Over the WebSocket a performer in a room speaks with WebCodecs (voice_ws.js) while #mic
 *  is ticked; no reconnection needed. Says so when the browser cannot. */
async function wsMicrophone(session) {
  wsMic?.stop();
  wsMic = null;
  if (!$("mic").checked || state.room?.role !== "perform" || session !== state.session) return;
  const missing = voiceUnsupported();
  if (missing) {
    $("mic").checked = false;
    $("mic-status").textContent = `no voice over the WebSocket: ${missing}`;
    return;
  }
  const mic = new WsMicrophone((data, tCapture, level) => session.voice(data, tCapture, level));
  mic.setMuted(voices.micMuted);
  try {
    await mic.start(await openMicrophone(), session.welcome?.voice);
  } catch (err) {
    mic.stop();
    $("mic").checked = false;
    $("mic-status").textContent = `microphone unavailable: ${err.message}`;
    return;
  }
  if (session !== state.session) return mic.stop();  // the page moved on meanwhile
  wsMic = state.wsMic = mic;
  $("mic-status").textContent = "speaking";
}

// ---- WebRTC: the private room of a solo page, the video's frames -------------------------

function forgetPrivateRoom({ keepalive = false } = {}) {
  if (state.privateRoom) deleteRoom(state.privateRoom, token, keepalive);
  state.privateRoom = null;
}

/** A WebRTC session: a solo page (an avatar id) WHEPs into a private room it makes, as its
 *  owner performing seat 0; a room page WHEPs into the room with its (invitation) token. */
async function whepSession(target) {
  let roomId = target.room;
  let query = { seat: target.seat, role: target.role };
  if (typeof target === "string") {
    forgetPrivateRoom();
    const room = await api("/v1/rooms", { method: "POST", body: { seats: [{ avatar: target }] } });
    state.privateRoom = roomId = room.id;
    query = { seat: 0 };
  }
  if (watchesMix(target)) query = { ...query, voice: "mix" };
  const size = Number($("size").value);
  const media = await voiceMedia(target);
  return new WhepSession(roomId, token, {
    video, stamps: true, query: { width: size, height: size, name: myName, ...query }, media,
    lipSync: params.get("lipsync") !== "0",
  });
}

/** A viewer of a room who ticked #voice-mix (?mix=1) hears one mix of every seat: WHEP
 *  `?voice=mix`, `hello.voice_mix` (its first voice line, or seatless `voice` messages). */
function watchesMix(target) {
  return typeof target !== "string" && target.role === "watch" && $("voice-mix").checked;
}

/** WebRTC refused or failed where the WebSocket may work (its limits, codecs, ICE): say so,
 *  switch to the WebSocket and connect again; false when there is nothing to fall back to. */
function fallBack(err, target) {
  if (state.transport !== "webrtc" || !worthFallingBack(err)) return false;
  notify(`WebRTC unavailable (${err.message}): using the WebSocket`, "error");
  forgetPrivateRoom();
  useTransport({ transport: "ws", why: `WebRTC failed: ${err.message}` });
  connect(target);
  return true;
}

async function pollRtcStats() {
  const session = state.session;
  if (session && !session.poll && state.room) {  // the WebSocket: voices decoded here
    state.voices = wsVoices.poll();
    $("speaking").textContent = wsVoices.speakingText();
    return;
  }
  if (!session?.poll || session.closed) return;
  state.voices = await voices.poll();
  $("speaking").textContent = voices.speakingText();
  try {
    state.stats.rtc = await session.poll();
  } catch { /* closed meanwhile */ }
}

// ---- reconnecting: one outage at a time ----------------------------------------------------

let retry = null;  // {attempt: tries made, lostAt, reason, timer} while reconnecting

function cancelRetry() {
  if (retry?.timer) clearTimeout(retry.timer);
  retry = null;
  state.reconnecting = false;
}

/** A session ended (`outcome`: {closeCode, errorCode} or {failure}): schedule the next try at
 *  `target`, or say why not. False when there is nothing to do (an ordinary end). */
function sessionEnded(target, outcome) {
  const decision = reconnect.attempts > 0 ? reconnectDecision(outcome) : null;
  if (decision === "stop") {
    cancelRetry();
    const why = stopReason(outcome);
    $("status").textContent = `disconnected: ${why}; not reconnecting`;
    notify(`not reconnecting: ${why}`, "error");
    if (unauthorized(outcome)) tokenRefused(why);
    return true;
  }
  if (decision !== "retry") return false;
  const attempt = retry?.attempt ?? 0;
  if (attempt >= reconnect.attempts) {
    cancelRetry();
    $("status").textContent = `could not reconnect in ${reconnect.attempts} tries: reload the page to try again`;
    return true;
  }
  const reason = retry?.reason ?? (outcome.errorCode === "restarting" ? "the server is restarting"
    : `the connection was lost (${outcome.closeCode ?? outcome.failure?.message})`);
  const delay = backoffDelay(attempt, reconnect);
  if (!retry) notify(`${reason}: reconnecting`, "error");
  retry = {
    attempt: attempt + 1, lostAt: retry?.lostAt ?? performance.now(), reason,
    timer: setTimeout(() => { retry.timer = null; connect(target, { retrying: true }); }, delay),
  };
  state.reconnecting = true;
  $("status").textContent = `${reason}: reconnecting in ${(delay / 1000).toFixed(1)} s (try ${attempt + 1} of ${reconnect.attempts})`;
  return true;
}

/** `target`: an avatar id (a private session) or {room, role, seat} (join a room).
 *  `retrying`: a try of the reconnection in progress (else a new connection ends it). */
async function connect(target, { retrying = false } = {}) {
  if (!retrying) cancelRetry();
  const previous = state.session;
  state.session = null;
  previous?.close();
  wsMic?.stop();
  wsMic = null;
  wsVoices.stop();
  player.stop();
  const inRoom = typeof target !== "string";
  state.avatar = inRoom ? null : target;
  state.room = null;
  state.stats.rtc = null;
  $("status").textContent = `connecting to ${inRoom ? `room ${target.room}` : target}…`;
  let session;
  try {
    session = state.transport === "webrtc" ? await whepSession(target)
      : new Session(streamUrl(target), token,
        inRoom ? { ...target, voice: !voiceUnsupported(), voiceMix: watchesMix(target) } : {},
        myName);
  } catch (err) {
    if (retrying && sessionEnded(target, { failure: err })) return;
    if (!fallBack(err, target)) $("status").textContent = `could not connect: ${err.message}`;
    if (unauthorized(err)) tokenRefused(err.message);
    return;
  }
  state.session = session;
  let rejoin = null;      // after the welcome: the same room, role and seat
  let lastError = null;   // the last error that answered nothing (restarting, gone, ...)
  session.addEventListener("presence", (e) => showPresence(e.detail));
  session.addEventListener("avatar", (e) => showReplacedAvatar(e.detail.avatar));
  session.addEventListener("frame", (e) => showFrame(e.detail));
  session.addEventListener("voice", (e) => wsVoices.packet(e.detail));
  session.addEventListener("servererror", (e) => {
    if (!e.detail.answers) lastError = e.detail.code;
    onServerError(e.detail);
  });
  session.addEventListener("stats", (e) => { state.stats.server = e.detail; });
  session.addEventListener("pong", (e) => { state.stats.rttMs = e.detail.rttMs; });
  session.addEventListener("shown", (e) => state.stats.latency(e.detail.latencyMs));
  session.addEventListener("tracked", (e) => {
    state.tracked = e.detail;
    if (webcam.running) $("webcam-status").textContent = trackedText(e.detail);
  });
  session.addEventListener("close", (e) => {
    if (state.session !== session) return;
    if (rejoin && sessionEnded(rejoin, { closeCode: e.detail.code, errorCode: lastError })) return;
    $("status").textContent = `disconnected (${e.detail.code}) ${e.detail.reason}`;
  });
  try {
    const welcome = await session.ready;
    const info = welcome.avatar;
    state.avatar = info.id;
    state.room = welcome.room ?? null;
    const solo = !state.room || state.room.id === state.privateRoom;
    $("room-bar").hidden = solo;
    $("avatar").disabled = !solo;
    setViewer(state.room?.role === "watch");
    $("status").textContent = statusLine({
      avatar: info, room: state.room, solo, session: welcome.session, transport: state.transport,
    });
    controls.build(info.expression_names || [], welcome.limits);
    showBackground(welcome.request?.background);
    sendRequest();
    // A new scene starts from its default framing; a reconnection keeps the view it had.
    if (JSON.stringify(welcome.framing ?? null) !== JSON.stringify(orbit.framing)) {
      orbit.setFraming(welcome.framing, welcome.limits);
    }
    session.view(orbit.current(), false);
    session.ping();
    if (state.transport !== "webrtc" && !solo) {
      wsVoices.pictureSeat = state.room.seat ?? target.seat ?? 0;  // whose t_capture frames carry
      const missing = voiceUnsupported();
      if (missing) $("mic-status").textContent = `no voice over the WebSocket: ${missing}`;
      $("voices").textContent = missing ? `voices cannot play here: ${missing}` : "";
      wsMicrophone(session);
    }
    rejoin = solo ? target : {
      room: state.room.id, role: state.room.role,
      seat: state.room.role === "perform" ? state.room.seat : target.seat,
    };
    state.rejoin = rejoin;
    if (retry) {
      state.reconnects += 1;
      state.lastReconnect = {
        reason: retry.reason, downMs: performance.now() - retry.lostAt, attempts: retry.attempt,
      };
      notify(`reconnected after ${(state.lastReconnect.downMs / 1000).toFixed(1)} s`);
      cancelRetry();
    }
  } catch (err) {
    if (state.session !== session) return;
    if (retrying && sessionEnded(target, { failure: err })) return;
    if (fallBack(err, target)) return;
    $("status").textContent = `could not connect: ${err.code ? `${err.code}: ` : ""}${err.message}`;
    if (unauthorized(err)) tokenRefused(err.message);
  }
}

// ---- panels -----------------------------------------------------------------------------

async function listAvatars() {
  const body = await api("/v1/avatars");
  return Array.isArray(body) ? body : body.avatars;
}

function fillAvatars(avatars, selected) {
  const select = $("avatar");
  select.replaceChildren(...avatars.map((a) => new Option(`${a.name || a.id} (${a.id})`, a.id)));
  if (avatars.some((a) => a.id === selected)) select.value = selected;
}

async function loadAvatars() {
  let avatars;
  try {
    avatars = await listAvatars();
  } catch (err) {
    $("status").textContent = `cannot list avatars: ${err.message}`;
    if (unauthorized(err)) tokenRefused(err.message);
    return;
  }
  if (!avatars.length) {
    $("status").textContent = "no avatars on this server yet";
    return;
  }
  const wanted = params.get("avatar");
  fillAvatars(avatars, avatars.some((a) => a.id === wanted) ? wanted : avatars[0].id);
  await connect($("avatar").value);
}

// ---- make my avatar (enroll.js): record, upload, follow the job, offer the result -------

async function makeAvatar() {
  const upload = $("enroll-upload");
  upload.disabled = true;
  $("enroll-show").hidden = true;
  try {
    const job = await enrollment.upload($("enroll-name").value.trim());
    notify(`enrollment job ${job.id} accepted`);
    const end = await enrollment.follow(job.id);
    if (end.state !== "succeeded") {
      notify(`your avatar could not be made: ${end.error ?? end.state}`, "error");
      return;
    }
    const solo = !state.room || state.room.id === state.privateRoom;
    if (solo) fillAvatars(await listAvatars(), state.avatar);  // the new one is in the list
    $("enroll-show").hidden = !solo;
    notify(`your avatar ${end.avatar_id} is ready${solo ? ": pick it in the Avatar list" : ""}`);
  } catch (err) {
    if (unauthorized(err)) tokenRefused(err.message);
    notify(`cannot make the avatar: ${err.message}`, "error");
  } finally {
    upload.disabled = !enrollment.blob;
  }
}

function wireEnrollment() {
  const [record, stop, upload] = ["enroll-record", "enroll-stop", "enroll-upload"].map($);
  record.addEventListener("click", async () => {
    record.disabled = true;
    upload.disabled = true;
    stop.disabled = false;
    try {
      await enrollment.record();
    } catch (err) {
      enrollment.status(`camera unavailable: ${err.message}`, "error");
    } finally {
      record.disabled = false;
      stop.disabled = true;
      upload.disabled = !enrollment.blob;
    }
  });
  stop.addEventListener("click", () => enrollment.stop());
  upload.addEventListener("click", makeAvatar);
  $("enroll-show").addEventListener("click", () => {
    const id = enrollment.state.avatarId;
    if (!id) return;
    $("avatar").value = id;
    connect(id);
  });
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

async function share() {
  const button = $("share");
  button.disabled = true;
  try {
    if (state.room && state.room.id === state.privateRoom) {  // WebRTC: share the private room
      state.privateRoom = null;
      $("avatar").disabled = true;
      const url = new URL(location.href);
      url.searchParams.delete("avatar");
      url.searchParams.set("room", state.room.id);
      history.replaceState(history.state, "", url.toString());
    }
    if (!state.room) {  // a room for the avatar on screen; this page performs its seat 0
      const room = await api("/v1/rooms", { method: "POST", body: { seats: [{ avatar: state.avatar }] } });
      await connect({ room: room.id, role: "perform", seat: 0 });
      if (!state.room) throw new Error("could not join the new room");
      const url = new URL(location.href);
      url.searchParams.delete("avatar");
      url.searchParams.set("room", room.id);
      history.replaceState(history.state, "", url.toString());
    }
    const mySeat = state.room.role === "perform" ? state.room.seat : null;
    state.shareLinks = await inviteAll(api, state.room.id, mySeat, location.origin);
    showLinks($("share-links"), state.shareLinks);
    $("room-bar").hidden = false;
    state.rejoin = { room: state.room.id, role: state.room.role, seat: state.room.seat };
    $("status").textContent = statusLine({  // now a room, not a session
      avatar: state.session.welcome.avatar, room: state.room, solo: false,
      session: state.session.welcome.session, transport: state.transport,
    });
  } catch (err) {
    notify(`cannot share: ${err.message}`, "error");
  } finally {
    button.disabled = false;
  }
}

function wire() {
  fitToViewport($("stage"));
  wireEnrollment();
  wireViewBar({
    view: orbit, capture, notify,
    sendBackground: (background) => state.session?.request({ background }),
  });
  $("share").hidden = !canShare(token);
  $("share").addEventListener("click", share);
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
      $("webcam-status").textContent = "sending frames…";  // until the first `tracked`
    } catch (err) {
      e.target.checked = false;
      $("webcam-status").textContent = `camera unavailable: ${err.message}`;
    }
  });
  overlayToggle($("stats-toggle"), $("stats"));
  $("mic").checked = params.get("mic") === "1";
  $("mic").addEventListener("change", () => {  // WHEP cannot renegotiate: join again
    if (!$("mic").checked) $("mic-status").textContent = "off";
    if (state.transport !== "webrtc") wsMicrophone(state.session);  // the WebSocket can
    else if (state.room) connect({ room: state.room.id, role: state.room.role, seat: state.room.seat });
  });
  $("voice-mix").checked = params.get("mix") === "1";
  $("voice-mix").addEventListener("change", () => {  // the server mixes per join: join again
    if (state.room && state.room.role !== "watch") {
      $("voice-mix").checked = false;
      notify("the mixed voice is for viewers: a performer hears each seat on its own", "error");
    }
    voices.mixed = wsVoices.mixed = $("voice-mix").checked;
    if (state.room?.role === "watch") {
      connect({ room: state.room.id, role: state.room.role, seat: state.room.seat });
    }
  });
  voices.mixed = wsVoices.mixed = $("voice-mix").checked;
  document.addEventListener("pointerdown", () => wsVoices.resume());  // autoplay rules
  $("mic-mute").addEventListener("click", () => {
    voices.setMicMuted(!voices.micMuted);
    wsMic?.setMuted(voices.micMuted);
    $("mic-mute").textContent = voices.micMuted ? "Unmute" : "Mute";
  });
  setInterval(() => renderStats($("stats"), state.stats.summary()), 250);
  $("my-name").value = myName ?? "";
  $("my-name").addEventListener("change", (e) => {  // joins again under the new name
    try {
      myName = storeName(e.target.value, state.session?.welcome?.limits?.max_name_chars);
    } catch (err) {
      notify(`cannot use that name: ${err.message}`, "error");
      return;
    }
    if (state.rejoin) connect(state.rejoin);
  });
  setInterval(() => state.session?.ping(), 1000);
  setInterval(pollRtcStats, 1000);
  // Leaving the page ends the peer (DELETE of the WHEP resource) and the solo page's room.
  window.addEventListener("pagehide", () => {
    state.session?.close();
    enrollment.close();
    forgetPrivateRoom({ keepalive: true });
  });
}

/** WebRTC or the WebSocket (see chooseTransport); shows the one chosen. */
async function pickTransport() {
  const choice = chooseTransport(params.get("transport"), typeof RTCPeerConnection === "function",
    await serverHealth());
  useTransport(choice);
  if (choice.transport === "webrtc") onVideoFrame(video, () => { state.framesShown += 1; });
}

function useTransport(choice) {
  state.transport = choice.transport;
  state.transportWhy = choice.why;
  state.stats.transport = choice.transport === "webrtc" ? "webrtc" : "websocket";
  canvas.hidden = choice.transport === "webrtc";
  video.hidden = !canvas.hidden;
}

async function joinRoom(roomId) {
  // A viewer may ask to watch with a perform link (?role=watch); otherwise the token decides.
  // ?mix=1 (the room's one mixed voice) is for viewers: it watches too.
  const watches = params.get("role") === "watch" || params.get("mix") === "1";
  const role = watches ? "watch" : undefined;
  await connect({ room: roomId, role });
  const info = state.session?.welcome?.avatar;
  if (info) $("avatar").replaceChildren(new Option(`${info.name || info.id} (${info.id})`, info.id));
  if (state.room?.role === "perform") loadMotions();
}

/** The avatar shown was replaced in place (the trained demo, swapped in by the server on
 *  this same connection): its name and controls follow. */
function showReplacedAvatar(info) {
  if (info.id !== state.avatar) return;
  const status = $("status").textContent;
  const rest = status.includes(" Gaussians, ") ? status.slice(status.indexOf(" Gaussians, ")) : "";
  $("status").textContent = `${info.name} — ${info.num_gaussians}${rest}`;
  controls.build(info.expression_names || [], state.session?.welcome?.limits);
  if (state.room && state.room.id !== state.privateRoom) {
    $("avatar").replaceChildren(new Option(`${info.name || info.id} (${info.id})`, info.id));
  }
}

/** The trained demo's background build: a banner while it runs. When it is done the server
 *  swaps it into every session and room showing the stand-in (an "avatar" message). */
function followDemoBuild() {
  const banner = $("demo-build");
  watchDemoBuild({
    fetchStatus: () => api("/v1/demo"),
    show: (status) => {
      state.demoBuild = status;
      const text = demoBanner(status);
      banner.hidden = !text;
      banner.textContent = text || "";
      banner.className = status?.state === "failed" ? "error" : "";
    },
    onReady: () => notify("the trained demo avatar is ready"),
  });
}

async function start() {
  wire();
  followDemoBuild();
  if (!token) notify("no #token= in the address: the server prints a URL with one", "error");
  await pickTransport();
  if (params.get("room")) {
    joinRoom(params.get("room"));
  } else {
    loadAvatars();
    loadMotions();
  }
}

start();
