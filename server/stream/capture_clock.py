"""A performer's capture stamps on this server's clock: the stamp plus the quickest transit.

A performer stamps its drives (``t_capture``) and its voice (RTP timestamps, or a ``voice``
message's ``t_capture``) on clocks of its own. To put a drive and a voice packet on one clock
(the WebRTC senders' RTP timestamps and sender reports, server/webrtc/sender_clock.py), each
stamp is mapped to ``time.monotonic()`` here as ``stamp + min(arrival - stamp)`` over the last
``window_s``: the least-delayed sample is the truest (NTP's clock filter does the same), so a
late drive or a stalled packet moves nothing. The window lets the estimate follow a drifting
sender clock; a sample more than ``jump_s`` above the minimum means the sender's clock jumped
back (a restarted page, a new publisher) and the window starts again. Two paths from one
performer (its data channel and its RTP) differ by their least transit only: a few ms.
"""

from __future__ import annotations

import collections

WINDOW_S = 10.0  # the minimum is taken over this long (a drifting clock is followed)
JUMP_S = 1.0     # a transit this much above the minimum: the sender's clock jumped back


class ArrivalClock:
    def __init__(self, window_s: float = WINDOW_S, jump_s: float = JUMP_S) -> None:
        if window_s <= 0 or jump_s <= 0:
            raise ValueError(f"window_s and jump_s must be > 0, got {window_s}, {jump_s}")
        self.window_s, self.jump_s = window_s, jump_s
        # (arrival, arrival - stamp), offsets increasing: the first is the window's minimum
        self._window: collections.deque[tuple[float, float]] = collections.deque()
        self.resets = 0  # clock jumps seen

    def observe(self, stamp: float, arrived: float) -> float:
        """Note a sample stamped ``stamp`` that arrived at ``arrived`` (monotonic); its
        capture instant on this server's clock."""
        offset = arrived - stamp
        if self._window and offset - self._window[0][1] > self.jump_s:
            self._window.clear()
            self.resets += 1
        while self._window and self._window[-1][1] >= offset:
            self._window.pop()
        self._window.append((arrived, offset))
        while self._window[0][0] < arrived - self.window_s:
            self._window.popleft()
        # the quickest transit is at most this sample's: captured no later than it arrived
        # (min: float rounding of stamp + (arrived - stamp) can land 1e-9 ms past it)
        return min(stamp + self._window[0][1], arrived)

    def stamp_of(self, at: float) -> float | None:
        """The inverse: instant ``at`` on this server's clock as a stamp of the sender's clock
        (None before a sample)."""
        return None if not self._window else at - self._window[0][1]

    def reset(self) -> None:
        """The sender changed: forget what its clock was."""
        self._window.clear()
