"""Avatar packages the server can stream: ``<root>/<id>/{record.json, package/}``.

A package is validated with ``load_package`` before anything lands in the registry, copied to a
temporary folder inside ``root`` and renamed into place, so a reader never sees half an
avatar and a failed add leaves nothing behind. Records (owner, name, metadata) survive
restarts. Loaded avatars are cached; each streaming session gets its own animator (posing
is stateful) over the shared, read-only model tensors.

Everything stored is private to the server's user (folders 0700, files 0600), and no server
path reaches a client: path-like strings are scrubbed from a package's manifest and record
(a trainer records its dataset's folder), and a demo avatar from a path is "demo:package".

Beyond its value ranges, an avatar is checked at its rest pose, at upload and when a stored
one is opened (:meth:`AvatarRegistry.check_at_rest`): no splat larger than the body
(``gaussian_ranges.max_splat_body_ratio``, ``validate.check_splat_extent``), and a frame of
it from the default orbit at the largest output the server allows needs at most
``max_avatar_tile_pairs`` (Gaussian, tile) pairs (``render.cost``), so that an avatar whose
every value is in range cannot be a render bomb.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import secrets
import shutil
import tempfile
import threading
import time
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from avatar_core.body.cache import StageCache
from avatar_core.body.errors import ModelFileError
from avatar_core.body.model_paths import BodyModelsMissing, models_for_reference
from avatar_core.bounded_npz import NpzLimits
from avatar_core.gaussians.animate import AvatarAnimator
from avatar_core.gaussians.loading import (
    BodyModelMismatch,
    LoadedAvatar,
    check_binding,
    load_avatar,
    upper_body_faces,
    upper_body_model,
)
from avatar_core.gaussians.package import (
    GAUSSIANS,
    MANIFEST,
    MAX_PACKAGE_BYTES,
    AvatarPackage,
    PackageError,
    load_package,
    save_package,
)
from avatar_core.gaussians.validate import GaussianRanges, RangeError, check_splat_extent
from avatar_core.render.camera_path import framing_target
from avatar_core.render.cost import frame_tile_pairs
from protocol import Orbit, View

from .auth import PUBLIC_OWNER
from .private import make_private, private_dir
from .stream.scene import view_camera

log = logging.getLogger(__name__)
RECORD, PACKAGE_DIR = "record.json", "package"
ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")
DEMO_ID = "demo"
STAND_IN_SOURCE = "demo:trained-pending"  # the synthetic demo while the trained one is built
_PATH_LIKE = re.compile(r"^(/|~|\\\\|[A-Za-z]:[\\/])")  # /abs, ~user, \\share, C:\


class AvatarNotFound(KeyError):
    pass


class StorageQuotaExceeded(ValueError):
    """The package would take its owner past their storage quota."""


def scrub_paths(value: Any) -> Any:
    """``value`` (JSON) without server paths: dict entries holding a path are dropped, list
    items holding one become its last component."""
    if isinstance(value, dict):
        return {k: scrub_paths(v) for k, v in value.items()
                if not (isinstance(v, str) and _PATH_LIKE.match(v))}
    if isinstance(value, list):
        return [Path(v).name if isinstance(v, str) and _PATH_LIKE.match(v) else scrub_paths(v)
                for v in value]
    return value


@dataclass
class AvatarRecord:
    id: str
    name: str
    owner: str
    num_gaussians: int
    sh_degree: int
    created: float
    size_bytes: int
    source: str = ""  # where it came from (a demo spec, a job id, "upload")
    metadata: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class RestFrameLimit:
    """A frame of an avatar at its rest pose, from the default orbit (``View(orbit=Orbit())``,
    what a session starts with) at ``width`` x ``height`` (the largest output), may need at
    most ``max_tile_pairs`` (Gaussian, tile) pairs."""

    max_tile_pairs: int
    width: int
    height: int


def _dir_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


class AvatarRegistry:
    """Avatar packages under ``root``, with owners; thread-safe."""

    def __init__(self, root: str | Path, *, max_package_bytes: int = MAX_PACKAGE_BYTES,
                 npz_limits: NpzLimits | None = None,
                 ranges: GaussianRanges | None = None,
                 body_models: str | Path | None = None,
                 rest_frame: RestFrameLimit | None = None) -> None:
        self.root = private_dir(root)
        # the setting body_models, which already ranks file < TELESPLAT_BODY_MODELS < flag, so
        # it goes to the resolver as the explicit folder (None: the resolver's own order)
        self.body_models = body_models
        self.ranges = ranges  # None: GaussianRanges' defaults
        self.rest_frame = rest_frame  # None: a rest frame's pairs are not checked
        self.max_package_bytes = max_package_bytes
        self.npz_limits = npz_limits  # None: load_package's, from max_package_bytes
        self._lock = threading.RLock()
        self._records: dict[str, AvatarRecord] = {}
        self._loaded: dict[str, LoadedAvatar] = {}
        self._load_locks: dict[str, threading.Lock] = {}
        self._scan()

    @classmethod
    def from_settings(cls, settings: Any) -> AvatarRegistry:
        """The server's registry: ``settings.avatars_dir``, its unpack limits and the
        ``body_models`` setting."""
        limits = NpzLimits(max_array_bytes=settings.max_npz_array_bytes,
                           max_total_bytes=settings.max_npz_bytes,
                           max_ratio=settings.max_unpack_ratio)
        rest_frame = RestFrameLimit(settings.max_avatar_tile_pairs, settings.limits.max_width,
                                    settings.limits.max_height)
        # the files together may be larger than the zip, and hold the arrays and the manifest
        return cls(settings.avatars_dir, npz_limits=limits, ranges=settings.gaussian_ranges,
                   max_package_bytes=max(4 * settings.max_upload_bytes, settings.max_npz_bytes),
                   body_models=settings.body_models, rest_frame=rest_frame)

    # -- records ---------------------------------------------------------------------------

    def _scan(self) -> None:
        for rec_file in sorted(self.root.glob(f"*/{RECORD}")):
            try:
                rec = AvatarRecord(**json.loads(rec_file.read_text()))
            except (ValueError, TypeError):
                continue  # a damaged record is skipped, not fatal
            if rec.id == rec_file.parent.name:
                rec.metadata = scrub_paths(rec.metadata)  # records written before scrubbing
                if rec.source.startswith("demo:") and _PATH_LIKE.match(rec.source[5:]):
                    rec.source = "demo:package"
                with contextlib.suppress(OSError, ValueError, AttributeError):
                    _scrub_manifest(rec_file.parent / PACKAGE_DIR / MANIFEST)
                self._records[rec.id] = rec
        for tmp in self.root.glob(".incoming-*"):  # leftovers of a crash mid-add
            shutil.rmtree(tmp, ignore_errors=True)

    def package_dir(self, avatar_id: str) -> Path:
        return self.root / avatar_id / PACKAGE_DIR

    def get(self, avatar_id: str) -> AvatarRecord:
        with self._lock:
            rec = self._records.get(avatar_id) if isinstance(avatar_id, str) else None
        if rec is None:
            raise AvatarNotFound(avatar_id)
        return rec

    def list(self, owner: str | None = None, *, include_public: bool = False
             ) -> list[AvatarRecord]:
        """Records of ``owner`` (all when None), plus the public ones if asked, oldest first."""
        with self._lock:
            recs = list(self._records.values())
        if owner is not None:
            owners = {owner, PUBLIC_OWNER} if include_public else {owner}
            recs = [r for r in recs if r.owner in owners]
        return sorted(recs, key=lambda r: (r.created, r.id))

    # -- adding and removing -----------------------------------------------------------------

    def add_package(self, src: str | Path, owner: str, name: str | None = None, *,
                    avatar_id: str | None = None, source: str = "",
                    metadata: dict[str, Any] | None = None,
                    max_size_bytes: int | None = None,
                    check_rest_now: bool = True) -> AvatarRecord:
        """Validate a package (folder or zip) and copy it in atomically; PackageError if bad,
        StorageQuotaExceeded when it unpacks to more than ``max_size_bytes`` (None: no cap).

        ``avatar_id``: a fixed id (replaces an avatar of that id), else a fresh random one.
        ``check_rest_now=False`` leaves :meth:`check_at_rest` to the first :meth:`open`, which
        runs it for every avatar before any frame: for the server's own synthetic demo, whose
        check would compile numba's posing and tile kernels before the server answers (55 of
        the 60 s of registering it on a fresh clone at load 6; docs/benchmarks.md).
        """
        src = Path(src)
        package = load_package(src, max_bytes=self.max_package_bytes,
                               npz_limits=self.npz_limits, ranges=self.ranges)  # PackageError
        self._check_body(package)
        model = upper_body_model(models_for_reference(package.body.model, self.body_models))
        if check_rest_now:
            self.check_at_rest(AvatarAnimator(model, package.avatar,
                                              betas=np.asarray(package.body.betas),
                                              cache=StageCache(enabled=False)))
        avatar_id = avatar_id or secrets.token_hex(8)
        if not ID_PATTERN.match(avatar_id):
            raise ValueError(f"bad avatar id {avatar_id!r}")
        staging = Path(tempfile.mkdtemp(prefix=".incoming-", dir=self.root))
        try:
            target = staging / PACKAGE_DIR
            target.mkdir()
            if src.is_dir():
                for member in (MANIFEST, GAUSSIANS):
                    shutil.copyfile(src / member, target / member)
            else:
                _extract_members(src, target)
            _scrub_manifest(target / MANIFEST)
            size = _dir_size(target)
            if max_size_bytes is not None and size > max_size_bytes:
                raise StorageQuotaExceeded(
                    f"storage quota exceeded: the avatar takes {size} bytes and "
                    f"{max(0, max_size_bytes)} are left")
            rec = AvatarRecord(
                id=avatar_id, name=name or package.name, owner=owner,
                num_gaussians=package.avatar.num, sh_degree=package.avatar.sh_degree,
                created=time.time(), size_bytes=size, source=source,
                metadata=scrub_paths({**package.metadata, **(metadata or {})}))
            (staging / RECORD).write_text(json.dumps(rec.to_dict(), indent=2))
            make_private(staging)
            with self._lock:
                final = self.root / avatar_id
                if final.exists():
                    self._remove_dir(final)
                staging.rename(final)
                self._records[avatar_id] = rec
                self._loaded.pop(avatar_id, None)
            return rec
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    def _check_body(self, package: AvatarPackage) -> None:
        """PackageError unless this server's body models are the ones the package is bound to
        (checked again when it is opened: the setting may change between restarts). The full
        reason, which names server folders, goes to the log only."""
        try:
            files = models_for_reference(package.body.model, self.body_models)
            check_binding(package.body, files, upper_body_faces(files), "the package")
        except BodyModelMismatch as exc:
            log.warning("avatar package refused: %s", exc)
            raise BodyModelMismatch(exc.public) from None
        except ModelFileError as exc:  # no folder set, it lacks a file, or one is unreadable
            log.warning("avatar package refused: %s", exc)
            raise PackageError(f"it is bound to body model {package.body.model!r}, which this "
                               "server does not have") from None

    def check_at_rest(self, animator: AvatarAnimator) -> None:
        """PackageError unless the avatar, posed at rest by ``animator``, has no splat larger
        than the body (``ranges.max_splat_body_ratio``) and, with ``rest_frame``, a frame of it
        from the default orbit at the largest output fits ``rest_frame.max_tile_pairs``."""
        with torch.no_grad():
            posed = animator.pose()
        try:
            check_splat_extent(posed.gaussians.scales, posed.vertices, self.ranges)
        except RangeError as exc:
            raise PackageError(str(exc)) from None
        limit = self.rest_frame
        if limit is None:
            return
        chest = framing_target(animator.body_model.joint_template)
        camera = view_camera(View(orbit=Orbit()), limit.width, limit.height, chest)
        pairs = frame_tile_pairs(posed.gaussians, camera)
        if pairs > limit.max_tile_pairs:
            raise PackageError(
                f"a frame of it at rest from the default view at {limit.width}x{limit.height} "
                f"(the largest output) needs {pairs} (Gaussian, tile) pairs, more than "
                f"max_avatar_tile_pairs {limit.max_tile_pairs}: its splats are too large or "
                "too many to render")

    def _remove_dir(self, path: Path) -> None:
        # Rename first so the id is free at once; then delete at leisure.
        trash = path.with_name(f".incoming-trash-{secrets.token_hex(4)}")
        path.rename(trash)
        shutil.rmtree(trash, ignore_errors=True)

    def delete(self, avatar_id: str) -> None:
        with self._lock:
            self.get(avatar_id)
            self._remove_dir(self.root / avatar_id)
            self._records.pop(avatar_id, None)
            self._loaded.pop(avatar_id, None)

    def write_zip(self, avatar_id: str, out: str | Path) -> Path:
        """The avatar's package as a zip (what an upload accepts)."""
        self.get(avatar_id)
        pkg = self.package_dir(avatar_id)
        out = Path(out)
        with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
            for member in (MANIFEST, GAUSSIANS):
                z.write(pkg / member, member)
        return out

    # -- the demo avatar ---------------------------------------------------------------------

    def register_demo(self, spec: str, *, cache: str | Path | None = None,
                      recipe: dict[str, Any] | None = None) -> AvatarRecord | None:
        """The start-up demo avatar (owner 'public', id 'demo'): 'synthetic[:N]', 'trained',
        'none' or a package path. Kept as is when already registered from the same synthetic
        spec.

        'trained' never trains here: the trained demo in the demo cache (``cache``, default
        the user's; built for ``recipe``) when it is there, else the synthetic avatar stands
        in (metadata ``trained: false``, ``stand_in: true``) until the background build
        (server/jobs/demo_build.py) replaces it through :meth:`register_trained_demo`."""
        if spec == "none":
            return None
        with self._lock:
            existing = self._records.get(DEMO_ID)
        if existing is not None and existing.source == f"demo:{spec}" and spec != "trained":
            return existing
        if spec == "synthetic" or spec.startswith("synthetic:"):
            return self._register_synthetic_demo(spec, f"demo:{spec}", {"trained": False})
        if spec == "trained":
            from avatar_core.studio_entry import demo_build_plan  # finds, never trains

            ready = demo_build_plan(cache, recipe).ready
            if ready is not None:
                return self.add_package(ready, PUBLIC_OWNER, avatar_id=DEMO_ID,
                                        source="demo:trained", metadata={"trained": True})
            if existing is not None and existing.source == STAND_IN_SOURCE:
                return existing
            return self._register_synthetic_demo("synthetic", STAND_IN_SOURCE,
                                                 {"trained": False, "stand_in": True})
        # a path: re-added at every start (cheap), and never shown to clients
        return self.add_package(Path(spec), PUBLIC_OWNER, avatar_id=DEMO_ID,
                                source="demo:package")

    def _register_synthetic_demo(self, spec: str, source: str,
                                 metadata: dict[str, Any]) -> AvatarRecord:
        loaded = load_avatar(spec, self.body_models)
        with tempfile.TemporaryDirectory(dir=self.root, prefix=".incoming-") as tmp:
            src = save_package(loaded.package, Path(tmp) / "pkg")
            return self.add_package(src, PUBLIC_OWNER, avatar_id=DEMO_ID, source=source,
                                    metadata=metadata, check_rest_now=False)

    def register_trained_demo(self, package: str | Path, cache: str | Path | None,
                              job_id: str) -> AvatarRecord:
        """The background build's trained package: installed in the demo cache (later starts
        and ``telesplat demo-avatar`` find it there) and registered as 'demo' in place of
        the stand-in. Sessions already streaming the stand-in keep their loaded copy."""
        from avatar_core.studio_entry import demo_build_plan, install_trained_demo

        root = demo_build_plan(cache).root
        installed = install_trained_demo(root, package)
        return self.add_package(installed, PUBLIC_OWNER, avatar_id=DEMO_ID,
                                source="demo:trained",
                                metadata={"trained": True, "job_id": job_id})

    # -- loading for streaming ---------------------------------------------------------------

    def open(self, avatar_id: str) -> LoadedAvatar:
        """The loaded avatar (package + animator), cached. Its animator is shared: sessions
        should use :meth:`new_animator` instead of posing with it."""
        self.get(avatar_id)
        with self._lock:
            lock = self._load_locks.setdefault(avatar_id, threading.Lock())
        with lock:  # one load per avatar, even when many sessions start at once
            with self._lock:
                loaded = self._loaded.get(avatar_id)
            if loaded is None:
                # the limits it was accepted under: a package that was added also opens
                try:
                    loaded = load_avatar(str(self.package_dir(avatar_id)),
                                         body_models=self.body_models,
                                         max_bytes=self.max_package_bytes,
                                         npz_limits=self.npz_limits, ranges=self.ranges)
                except BodyModelMismatch as exc:  # the full message names server folders
                    log.error("avatar %s: %s", avatar_id, exc)
                    raise BodyModelMismatch(f"avatar {avatar_id}: {exc.public}") from None
                except BodyModelsMissing as exc:
                    log.error("avatar %s: %s", avatar_id, exc)
                    raise BodyModelsMissing(f"avatar {avatar_id}: {exc.public}") from None
                try:  # stored under other limits, or before this check existed
                    self.check_at_rest(loaded.animator)
                except PackageError as exc:
                    log.error("avatar %s: %s", avatar_id, exc)
                    raise PackageError(f"avatar {avatar_id}: {exc}") from None
                with self._lock:
                    if avatar_id in self._records:
                        self._loaded[avatar_id] = loaded
        return loaded

    def new_animator(self, avatar_id: str) -> tuple[LoadedAvatar, AvatarAnimator]:
        """A fresh animator for one session: the body model is shared (read-only), the stage
        cache and the animator's last-pose cache are the session's own."""
        loaded = self.open(avatar_id)
        base = loaded.animator
        cache = StageCache(enabled=base.body_model.cache.enabled)
        animator = AvatarAnimator(base.body_model, base.avatar, betas=base.betas, cache=cache)
        return loaded, animator


def _scrub_manifest(path: Path) -> None:
    """The copied package's avatar.json without server paths (it can be downloaded)."""
    manifest = json.loads(path.read_text())
    scrubbed = {k: v if k == "body_model" else scrub_paths(v) for k, v in manifest.items()}
    if scrubbed != manifest:
        path.write_text(json.dumps(scrubbed, indent=2))


def _extract_members(src: Path, target: Path) -> None:
    """Copy the two package members out of a zip that ``load_package`` has already checked."""
    with zipfile.ZipFile(src) as z:
        names = {Path(i.filename).name: i for i in z.infolist() if not i.is_dir()}
        for member in (MANIFEST, GAUSSIANS):
            with z.open(names[member]) as fin, open(target / member, "wb") as fout:
                shutil.copyfileobj(fin, fout, 1 << 20)


__all__ = ["DEMO_ID", "AvatarNotFound", "AvatarRecord", "AvatarRegistry", "PackageError",
           "RestFrameLimit", "StorageQuotaExceeded", "scrub_paths"]
