// Rooms on the page: the status line, the presence line and the display name this page joins
// with, and "Share" (the owner's page): a room for the current avatar if the page is not in
// one yet, then a watch invitation and a perform invitation per free seat, shown as absolute
// links with copy buttons. Invitation tokens are shown once, in those links; the server keeps
// only their hashes.

export const NAME_KEY = "telesplat.name";  // localStorage: the display name last chosen

/** The display name to join with: `?name=` in the address, else the one stored; null: the
 *  server's default ("performer", "viewer N"). The server validates it (protocol/names.py). */
export function chosenName(search, storage = window.localStorage) {
  const name = (new URLSearchParams(search).get("name") ?? storage.getItem(NAME_KEY) ?? "").trim();
  return name || null;
}

// The server's rule (protocol/names.py), checked here too so a bad name is never stored.
const NAME_CHARS = /^[\p{L}\p{N}_ .'-]+$/u;

/** Keep `name` for the next joins (blank: forget it); an Error saying why it cannot be. */
export function storeName(name, maxChars = 32, storage = window.localStorage) {
  const clean = name.trim().split(/\s+/).join(" ");
  if (clean.length > maxChars) throw new Error(`a name has at most ${maxChars} characters`);
  if (clean && !NAME_CHARS.test(clean)) {
    throw new Error("a name may hold letters, digits, spaces and . _ ' - only");
  }
  if (clean) storage.setItem(NAME_KEY, clean);
  else storage.removeItem(NAME_KEY);
  return clean || null;
}

/** How the status line names where the page is: "room Team sync" (a room's default name is
 *  already "room abc123": never "room room …"). */
export function roomLabel(room) {
  const name = room.name || room.id;
  return /^room\b/i.test(name) ? name : `room ${name}`;
}

/** The status line once connected: the avatar, where (a plain session or a room, and as
 *  what) and over which transport. `solo`: not (yet) shared, a plain or private session. */
export function statusLine({ avatar, room, solo, session, transport }) {
  const where = solo ? `session ${session}` : `${roomLabel(room)} (${room.role === "watch"
    ? "watching" : `performing seat ${room.seat}`})`;
  const over = transport === "webrtc" ? "WebRTC" : "WebSocket";
  return `${avatar.name} — ${avatar.num_gaussians} Gaussians, ${where} (${over})`;
}

/** "Ann joined (watching)" for a presence message that tells of a join or leave; null else. */
export function presenceNote(presence) {
  if (!presence?.who || !["join", "leave"].includes(presence.event)) return null;
  const as = presence.role === "watch" ? "watching" : "performing";
  return presence.event === "join" ? `${presence.who} joined (${as})` : `${presence.who} left`;
}

/** "seat 0 (demo): Ann performing, speaking · 2 watching" from a presence message. */
export function presenceText(presence) {
  if (!presence) return "";
  const seats = presence.seats.map((seat) => {
    const speaking = seat.speaking ? ", speaking" : "";
    const who = seat.performer ? `${seat.performer} performing${speaking}`
      : seat.holding ? "performer gone, holding the pose" : "free";
    return `seat ${seat.index} (${seat.avatar}): ${who}`;
  });
  const viewers = `${presence.viewers} watching`;
  return [...seats, viewers].join(" · ");
}

/** An invitation token (room-scoped, "tsr_…") cannot share: only the owner's token can. */
export function canShare(token) {
  return Boolean(token) && !token.startsWith("tsr_");
}

/** Invitations for `roomId`: watch, then perform for each seat nobody performs (not `mySeat`).
 *  Returns [{scope, seat, url}] with absolute page URLs. */
export async function inviteAll(api, roomId, mySeat, origin) {
  const room = await api(`/v1/rooms/${encodeURIComponent(roomId)}`);
  const invite = (body) => api(`/v1/rooms/${encodeURIComponent(roomId)}/invitations`,
    { method: "POST", body });
  const links = [];
  const watch = await invite({ scope: "watch" });
  links.push({ scope: "watch", seat: null, url: new URL(watch.link, origin).href });
  for (const seat of room.seats) {
    if (seat.performer || seat.index === mySeat) continue;
    const perform = await invite({ scope: "perform", seat: seat.index });
    links.push({ scope: "perform", seat: seat.index, url: new URL(perform.link, origin).href });
  }
  return links;
}

/** The links as rows: a label, the URL in a read-only field, a copy button. */
export function showLinks(container, links) {
  container.replaceChildren(...links.map((link) => {
    const row = document.createElement("div");
    row.className = "link";
    row.dataset.scope = link.scope;
    if (link.seat !== null) row.dataset.seat = String(link.seat);
    const label = document.createElement("span");
    label.textContent = link.scope === "watch" ? "watch link" : `perform seat ${link.seat}`;
    const field = Object.assign(document.createElement("input"),
      { type: "text", readOnly: true, value: link.url });
    const copy = Object.assign(document.createElement("button"), { textContent: "Copy" });
    copy.addEventListener("click", async () => {
      try {
        await navigator.clipboard.writeText(link.url);
        copy.textContent = "Copied";
      } catch {  // no clipboard permission (http, headless): select it for Ctrl+C instead
        field.select();
        copy.textContent = "Press Ctrl+C";
      }
    });
    row.append(label, field, copy);
    return row;
  }));
}
