"""What the routes share: settings, tokens, avatars, rooms, where frames are made, metrics,
sessions, the job service. The app carries this one object (``app.state.ctx``;
server/dependencies.py)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from avatar_core.body.models import MANOModel
from avatar_core.gaussians.animate import AvatarAnimator
from avatar_core.gaussians.loading import mano_models
from avatar_core.motion.rig import model_rig

from .auth import Principal, TokenStore, is_invitation
from .config import Settings
from .metrics import ServerMetrics
from .registry import AvatarRegistry
from .rooms.registry import Invitation, RoomRegistry
from .stream.admission import Admission, SessionSlots
from .stream.scheduler import RenderScheduler
from .stream.tracking import SessionTracker
from .webrtc.registry import PeerRegistry

if TYPE_CHECKING:
    from avatar_core.motion.keyframes import Rig

    from .jobs.service import JobService
    from .stream.workers import FrameWorkers


@dataclass
class ServerContext:
    settings: Settings
    tokens: TokenStore
    registry: AvatarRegistry
    scheduler: RenderScheduler
    track_scheduler: RenderScheduler  # webcam images -> fitted parameters, off the renderers
    metrics: ServerMetrics
    slots: SessionSlots
    sessions: dict[str, Any] = field(default_factory=dict)  # id -> stream.session.Session
    local_token: str | None = None  # local auth mode: the admin token printed at start-up
    jobs: JobService | None = None  # set while the app's lifespan runs (server/routers/jobs.py)
    demo_build: Any = None  # the trained demo's background build (server/jobs/demo_build.py)
    motion_rigs: dict[str, Rig] = field(default_factory=dict)  # avatar id -> its motion rig
    # set once the warm-up frame is done (or skipped): first frames no longer wait on numba
    warmed: threading.Event = field(default_factory=threading.Event)
    admission: Admission = None  # type: ignore[assignment]  # made from settings below
    rooms: RoomRegistry = None  # type: ignore[assignment]  # made from settings below
    webrtc_peers: PeerRegistry = None  # type: ignore[assignment]  # made from settings below
    startup_links: dict[str, str] = field(default_factory=dict)  # the start-up room's
    render: FrameWorkers = None  # type: ignore[assignment]  # where frames are made
    # (render_backend: server/stream/workers.py, server/cluster_render/backend.py)
    _manos: dict[str, dict[str, MANOModel]] = field(default_factory=dict)
    _manos_lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        if self.admission is None:
            self.admission = Admission.from_settings(self.settings)
        if self.rooms is None:
            self.rooms = RoomRegistry(self.settings)
        if self.webrtc_peers is None:
            self.webrtc_peers = PeerRegistry(self.settings)

    def credential(self, token: str | None) -> tuple[Principal | None, Invitation | None]:
        """Whom a token names: a bearer token's principal, or a room invitation (valid ones
        only; (None, None) otherwise)."""
        if not token:
            return None, None
        if is_invitation(token):
            return None, self.rooms.resolve(token)
        return self.tokens.principal(token), None

    def session_models(self, avatar_id: str) -> tuple[AvatarAnimator, dict[str, MANOModel]]:
        """A session's own animator, plus the (shared, read-only) MANO models for fusion."""
        loaded, animator = self.registry.new_animator(avatar_id)
        with self._manos_lock:
            manos = self._manos.get(avatar_id)
            if manos is None:
                manos = self._manos[avatar_id] = mano_models(loaded)
        return animator, manos

    def rig(self, avatar_id: str) -> Rig:
        """The avatar's rig (its expression names, gestures), cached per app; loads the
        avatar (a race only computes one twice)."""
        rig = self.motion_rigs.get(avatar_id)
        if rig is None:
            loaded = self.registry.open(avatar_id)
            rig = self.motion_rigs[avatar_id] = model_rig(loaded.files,
                                                          loaded.animator.body_model)
        return rig

    def forget_models(self, avatar_id: str) -> None:
        """The avatar was replaced in place: its cached MANO models and motion rig go (the
        registry drops its loaded copy itself)."""
        with self._manos_lock:
            self._manos.pop(avatar_id, None)
        self.motion_rigs.pop(avatar_id, None)

    def session_tracker(self, avatar_id: str) -> SessionTracker:
        """A session's own webcam tracker, fitting on the avatar's (shared, read-only) body
        model with the avatar's identity; its models load on the first image."""
        base = self.registry.open(avatar_id).animator
        return SessionTracker(base.body_model, base.betas, self.settings.limits)
