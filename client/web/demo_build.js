// The trained demo avatar's background build (GET /v1/demo): the banner's text, and a
// bounded poll that reports each status and says when the build is done.

/** The banner's text for a /v1/demo status; null: no banner (off, ready, or unknown). */
export function demoBanner(status) {
  if (!status || typeof status !== "object") return null;
  if (status.state === "building") {
    const pct = Math.max(0, Math.min(100, Math.floor((Number(status.progress) || 0) * 100)));
    const stage = status.stage === "capture" ? "filming" : "training";
    return `building the trained demo avatar: ${pct}% (${stage}); the untrained one stands in`;
  }
  if (status.state === "failed") {
    return `the trained demo avatar could not be built: ${status.error || "unknown error"}`;
  }
  return null;
}

/** Poll `fetchStatus()` every `intervalMs` while the build runs (at most `maxPolls` times),
 *  calling `show(status)` each time and `onReady(status)` once when it turns ready after
 *  having been seen building. Resolves with the last status. */
export async function watchDemoBuild({
  fetchStatus, show, onReady, intervalMs = 2000, maxPolls = 10800,
  sleep = (ms) => new Promise((r) => setTimeout(r, ms)),
}) {
  let sawBuilding = false;
  let status = null;
  for (let i = 0; i < maxPolls; i += 1) {
    try {
      status = await fetchStatus();
    } catch {
      status = null;  // the server restarting: try again
    }
    show(status);
    if (status?.state === "building") sawBuilding = true;
    else if (status?.state === "ready") {
      if (sawBuilding) onReady?.(status);
      return status;
    } else if (status && status.state !== "building") return status;  // off or failed
    await sleep(intervalMs);
  }
  return status;
}
