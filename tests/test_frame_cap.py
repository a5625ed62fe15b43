"""The frame-rate cap as a rate (server/stream/frame_cap.py): a bound on frames over any span,
and at matched rates no waits or coalesced drives from a little jitter."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.stream.frame_cap import FrameRateCap


def loop(arrivals: list[float], fps: float, burst: int) -> tuple[list[float], int]:
    """The session's render loop in virtual time (rendering instant): each frame starts at
    the newest drive's arrival or at the cap's earliest start, whichever is later; drives
    that arrive while a frame waits are coalesced into it. Returns the frames' starts and
    the coalesced drives."""
    cap, starts, coalesced, i = FrameRateCap(burst), [], 0, 0
    while i < len(arrivals):
        start = max(arrivals[i], cap.earliest(fps))
        while i + 1 < len(arrivals) and arrivals[i + 1] <= start:  # merged, never queued
            i, coalesced = i + 1, coalesced + 1
        cap.started(start, fps)
        starts.append(start)
        i += 1
    return starts, coalesced


def test_burst_one_is_a_strict_interval():
    starts, _ = loop([0.0, 0.001, 0.002, 0.5, 0.51], fps=10, burst=1)
    assert np.allclose(starts, [0.0, 0.1, 0.5, 0.6])


def test_a_burst_lets_that_many_frames_start_back_to_back_then_the_rate_holds():
    cap = FrameRateCap(3)
    for _ in range(3):
        assert cap.earliest(10) <= 0.0
        cap.started(0.0, 10)
    assert cap.earliest(10) == pytest.approx(0.1)


@settings(max_examples=200, deadline=None)
@given(gaps=st.lists(st.floats(0, 0.2), min_size=1, max_size=80),
       fps=st.floats(1, 60), burst=st.integers(1, 8))
def test_no_span_holds_more_than_its_share_of_frames_plus_the_burst(gaps, fps, burst):
    starts, _ = loop(list(np.cumsum(gaps)), fps, burst)
    assert all(b >= a for a, b in zip(starts, starts[1:], strict=False))
    for i, first in enumerate(starts):
        for j in range(i, len(starts)):
            span = starts[j] - first
            assert j - i + 1 <= math.floor(span * fps + 1e-9) + burst


def test_matched_rates_with_jitter_wait_only_under_a_strict_interval():
    """A 30 Hz tracker with +-5 ms of arrival jitter into a 30 fps cap, 2 minutes of it: the
    strict interval locks the frames to the latest phase seen, so most drives wait; with a
    burst of 2 none does and none is merged."""
    rng = np.random.default_rng(0)
    arrivals = np.arange(3600) / 30 + rng.uniform(-0.005, 0.005, 3600)
    strict, _ = loop(list(arrivals), 30, burst=1)
    burst, burst_coalesced = loop(list(arrivals), 30, burst=2)
    assert np.mean(np.asarray(strict) - arrivals) > 0.003
    assert burst_coalesced == 0 and np.max(np.asarray(burst) - arrivals) < 1e-9


def test_after_a_network_stall_a_burst_catches_up_without_waiting():
    """In-order delivery: 5% of drives held 40 ms (the next ones queue behind them)."""
    rng = np.random.default_rng(1)
    held = np.where(rng.random(3600) < 0.05, 0.040, 0.0)
    arrivals = np.maximum.accumulate(np.arange(3600) / 30 + held)
    strict, strict_coalesced = loop(list(arrivals), 30, burst=1)
    burst, burst_coalesced = loop(list(arrivals), 30, burst=2)
    assert burst_coalesced <= strict_coalesced
    shown = np.unique(arrivals)  # drives that arrive together are one state: one frame
    assert len(burst) == len(shown) and np.max(np.asarray(burst) - shown) < 1e-9
    assert len(strict) < len(burst) or np.max(np.asarray(strict) - shown) > 0.005


def test_a_burst_below_one_is_refused():
    with pytest.raises(ValueError, match="burst"):
        FrameRateCap(0)


def test_a_new_rate_applies_at_once_to_the_wait_for_the_next_frame():
    """As with the strict interval before: a request's max_fps changes the pending wait."""
    cap = FrameRateCap(1)
    cap.started(0.0, 30)
    assert cap.earliest(1) == pytest.approx(1.0)
    assert cap.earliest(0.001) == pytest.approx(1000.0)
    assert cap.earliest(60) == pytest.approx(1 / 60)
    cap.started(1 / 60, 60)
    assert cap.earliest(60) == pytest.approx(2 / 60)
