"""The event loop's lag probe and stall log (server/loop_watch.py)."""

from __future__ import annotations

import asyncio
import gc
import logging
import threading
import time

import httpx

from server.loop_watch import GcWatch, LoopWatch, freeze_survivors
from server.metrics import ServerMetrics
from tests.server_fixtures import run_server


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


def gc_counts(metrics: ServerMetrics) -> dict[str, float]:
    return {sample.labels["generation"]: sample.value
            for metric in metrics.gc_pause_ms.collect() for sample in metric.samples
            if sample.name.endswith("_count")}


def test_each_collection_is_timed_by_generation_and_stop_unhooks() -> None:
    metrics = ServerMetrics()
    watch = GcWatch.into(metrics)
    hooks = len(gc.callbacks)
    watch.start()
    try:
        gc.collect(0)
        gc.collect(2)
    finally:
        watch.stop()
    counts = gc_counts(metrics)
    assert counts.get("0", 0) >= 1 and counts.get("2", 0) >= 1, counts
    assert len(gc.callbacks) == hooks
    gc.collect(2)
    assert gc_counts(metrics) == counts  # unhooked: nothing more observed


def test_frozen_survivors_are_out_of_the_collectors_walk() -> None:
    """What is alive when frozen is no longer walked by a full collection (the pause it
    saves is measured in bench/voice_sync.py; docs/benchmarks.md)."""
    kept = [[i] for i in range(100_000)]  # tracked containers, as a loaded library leaves
    walked = len(gc.get_objects())
    try:
        frozen = freeze_survivors()
        assert frozen >= len(kept)
        after = len(gc.get_objects())
        assert after <= walked - len(kept)
        fresh = [[i] for i in range(1000)]  # made since: walked as before
        assert len(gc.get_objects()) >= after + len(fresh)
    finally:
        gc.unfreeze()
    assert gc.get_freeze_count() == 0 and len(gc.get_objects()) >= len(kept)


def test_a_server_freezes_its_start_up_survivors_and_gives_them_back_at_stop(tmp_path) -> None:
    gc.unfreeze()
    with run_server(tmp_path, gc_freeze=True) as srv:
        frozen = gc.get_freeze_count()
        gc.collect(2)
        text = httpx.get(f"{srv.url}/metrics", headers=srv.headers(), timeout=30).text
    assert frozen > 10_000  # this process's libraries, at least
    assert 'telesplat_gc_pause_ms_count{generation="2"}' in text
    assert gc.get_freeze_count() == 0  # unfrozen at stop
