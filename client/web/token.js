// After a 401 (no token, an expired or rotated one, an invitation of a deleted room): a field
// to paste a token and try again, instead of a dead page. The pasted token goes where a
// #token= link puts it: the address's fragment, which the reloaded page takes into memory and
// removes at once (session.js, takeToken), so it is never stored, logged or sent in a URL.

/** Whether an error (an api() error with `status`, a ProtocolError with `code`) or a session
 *  end ({failure, errorCode, closeCode}) means the token was refused. */
export function unauthorized(what) {
  if (!what) return false;
  return what.status === 401 || what.code === "unauthorized" || what.errorCode === "unauthorized"
    || what.closeCode === 4401 || unauthorized(what.failure);
}

/** A token that looks pasteable: one line of printable characters (the server checks it). */
export function cleanToken(text) {
  const token = text.trim().replace(/^#?token=/, "");
  if (!token) throw new Error("paste a token first");
  if (token.length > 512) throw new Error("a token has at most 512 characters");
  if (!/^[\x21-\x7e]+$/.test(token)) throw new Error("a token has no spaces or special characters");
  return token;
}

/** Show `form` (an input and a submit button) with `why`; on submit the page reloads with
 *  the token in its fragment, as if opened from the link `telesplat serve` prints. */
export function askForToken(form, why, win = window) {
  form.hidden = false;
  form.querySelector("[data-why]").textContent = why;
  const input = form.querySelector("input");
  const problem = form.querySelector("[data-problem]");
  form.onsubmit = (event) => {
    event.preventDefault();
    try {
      const token = cleanToken(input.value);
      const url = new URL(win.location.href);
      const fragment = new URLSearchParams(url.hash.slice(1));
      fragment.set("token", token);
      url.hash = fragment.toString();
      win.history.replaceState(win.history.state, "", url.toString());
      win.location.reload();
    } catch (err) {
      problem.textContent = err.message;
    }
  };
  input.focus();
}
