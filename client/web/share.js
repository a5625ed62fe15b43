// Rooms on the page: the presence line, and "Share" (the owner's page): a room for the current
// avatar if the page is not in one yet, then a watch invitation and a perform invitation per
// free seat, shown as absolute links with copy buttons. Invitation tokens are shown once, in
// those links; the server keeps only their hashes.

/** "seat 0 (demo): telesplat-web performing · 2 watching" from a presence message. */
export function presenceText(presence) {
  if (!presence) return "";
  const seats = presence.seats.map((seat) => {
    const who = seat.performer ? `${seat.performer} performing`
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
