"""The event loop's lag probe and stall log (server/loop_watch.py)."""

from __future__ import annotations

import asyncio
import logging
import threading
import time

from server.loop_watch import LoopWatch
from server.metrics import ServerMetrics


def lag_counts(metrics: ServerMetrics) -> dict[str, float]:
    out = {}
    for metric in metrics.loop_lag_ms.collect():
        for sample in metric.samples:
            if sample.name.endswith("_bucket"):
                out[sample.labels["le"]] = sample.value
    return out


def a_blocking_callback() -> None:
    time.sleep(0.3)  # holds the loop, as a slow synchronous handler would


async def run_watch(watch: LoopWatch, block: bool) -> None:
    watch.start()
    await asyncio.sleep(0.1)
    if block:
        a_blocking_callback()
    await asyncio.sleep(0.15)
    await watch.stop()


def test_a_held_loop_shows_in_the_histogram_and_the_log_names_the_holder(caplog) -> None:
    metrics = ServerMetrics()
    watch = LoopWatch(metrics, interval_s=0.01, stall_ms=100)
    with caplog.at_level(logging.WARNING, logger="telesplat.server.loop"):
        asyncio.run(run_watch(watch, block=True))
    counts = lag_counts(metrics)
    assert counts["+Inf"] - counts["100.0"] >= 1  # one wake came 100+ ms late
    assert watch.worst_ms >= 200
    stalls = [r.getMessage() for r in caplog.records if "event loop held" in r.getMessage()]
    # once per stall, not once per look (it looks every 5 ms); a loaded machine may add others
    assert sum("a_blocking_callback" in m for m in stalls) == 1
    assert metrics.loop_stalls._value.get() == len(stalls)


def test_a_free_loop_logs_nothing_and_off_starts_no_thread(caplog) -> None:
    metrics = ServerMetrics()
    watch = LoopWatch(metrics, interval_s=0.01, stall_ms=0)
    before = threading.active_count()
    with caplog.at_level(logging.WARNING, logger="telesplat.server.loop"):
        asyncio.run(run_watch(watch, block=False))
    assert threading.active_count() == before
    assert not [r for r in caplog.records if "event loop held" in r.getMessage()]
    counts = lag_counts(metrics)
    assert counts["+Inf"] >= 5  # it sampled
    assert metrics.loop_stalls._value.get() == 0
