"""The WebRTC peers of a server, their limits, and their resources' ids.

A slot is reserved (``reserve``) before any SDP is parsed or any peer made, so the limits
bound the work a flood of offers can cause: ``webrtc_max_peers`` in all (503) and
``webrtc_max_peers_per_user`` per token subject or invitation (429; admins exempt).
"""

from __future__ import annotations

import asyncio
import secrets
import threading
from collections import Counter
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .peer import WebRTCPeer


class PeerRefused(Exception):
    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


class PeerRegistry:
    def __init__(self, settings) -> None:
        self.settings = settings
        self._lock = threading.Lock()
        self._holders: dict[str, str] = {}  # resource -> holder key (reserved or live)
        self._peers: dict[str, WebRTCPeer] = {}

    def reserve(self, holder: str, exempt: bool) -> str:
        """A new resource id held by ``holder``; PeerRefused past a limit."""
        s = self.settings
        with self._lock:
            if len(self._holders) >= s.webrtc_max_peers:
                raise PeerRefused(503, f"server busy: {len(self._holders)} WebRTC peers, the "
                                       "most it serves (webrtc_max_peers); try again later")
            held = Counter(self._holders.values())[holder]
            if not exempt and held >= s.webrtc_max_peers_per_user:
                raise PeerRefused(429, f"{held} WebRTC peers open with this token, the most "
                                       "one user may have (webrtc_max_peers_per_user); "
                                       "DELETE one first")
            resource = secrets.token_hex(8)
            self._holders[resource] = holder
        return resource

    def add(self, peer: WebRTCPeer) -> None:
        with self._lock:
            self._peers[peer.resource] = peer

    def release(self, resource: str) -> None:
        with self._lock:
            self._holders.pop(resource, None)
            self._peers.pop(resource, None)

    def get(self, resource: str) -> WebRTCPeer | None:
        with self._lock:
            return self._peers.get(resource)

    def peers(self) -> list[WebRTCPeer]:
        with self._lock:
            return list(self._peers.values())

    async def close_all(self, reason: str) -> None:
        """Every peer closed (server shutdown)."""
        await asyncio.gather(*(peer.close(reason) for peer in self.peers()),
                             return_exceptions=True)

    def __len__(self) -> int:
        with self._lock:
            return len(self._holders)
