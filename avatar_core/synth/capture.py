"""A multi-view capture session in the software studio, written as a dataset.

Each sequence is a chain of named library motions sampled at the rig's frame rate. Per frame,
the actor is posed once and every camera renders it (in worker threads: the mesh kernels and
PNG encoding release the GIL). The splits follow the paper's protocol:

- ``train``: the training sequences seen by all but the held-out camera(s);
- ``novel_view``: the training sequences seen by the held-out camera(s);
- ``self_reenactment``: the held-out sequences, all cameras;
- ``cross_identity``: the held-out motions performed by another identity (its own betas and
  images), for driving this subject's avatar with someone else's motion.

The parameters written are what a real studio's trackers would report (see
:mod:`.trackers`): a body tracker's SMPL-X plus exact FLAME face and MANO hand parameters,
which fusion turns back into the truth. ``trackers="exact"`` writes the true SMPL-X only.
``tracker_noise`` adds tracker errors that fusion cannot remove (:class:`.trackers.TrackerNoise`);
the true parameters are then also written, as ``sequences/<seq>/true_params.npz`` (SMPL-X
keys; :func:`true_params_path`), so an evaluation can drive the avatar with the truth.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..body.model_paths import BodyModelFiles
from ..body.skeleton import SMPLX_PART_NAMES, UPPER_BODY_PARTS
from ..dataset.format import CameraSpec
from ..dataset.imageio import write_atomic
from ..dataset.writer import DatasetWriter
from ..metrics.webcam import true_params_path
from ..motion.library import motion_sequence
from ..motion.rig import model_rig
from .actor import Actor, ActorView
from .model_writer import ensure_models
from .studio import RigCamera, StudioConfig, studio_rig
from .trackers import TrackerNoise, simulate_trackers

__all__ = ["CaptureSpec", "capture", "parse_sequences", "true_params_path"]


Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class CaptureSpec:
    """What to film. `sequences`: each a tuple of motion names played one after another."""

    sequences: tuple[tuple[str, ...], ...]
    identity: int = 0
    num_cameras: int = 17
    resolution: int = 512
    max_frames: int | None = None  # per sequence; None: the whole motion
    holdout_cameras: tuple[str, ...] | None = None  # None: default_holdout(rig), never front
    holdout_sequences: int = 1  # the last k sequences (when there are more than k)
    cross_identity: int | None = None  # None: no cross-identity sequences
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    supersample: int = 2
    workers: int = 2
    trackers: str = "simulated"  # "simulated": body/face/hand tracker split; "exact": truth
    tracker_noise: TrackerNoise = field(default_factory=TrackerNoise)  # simulated only
    seed: int = 0
    studio: StudioConfig = field(default_factory=StudioConfig)

    def __post_init__(self) -> None:
        if not self.sequences or any(not s for s in self.sequences):
            raise ValueError("give at least one sequence, each of at least one motion")
        if self.max_frames is not None and self.max_frames < 1:
            raise ValueError("max_frames must be at least 1")
        # A single sequence is all training data; otherwise keep at least one for training.
        if self.holdout_sequences < 0 or (
                len(self.sequences) > 1 and self.holdout_sequences >= len(self.sequences)):
            raise ValueError(f"cannot hold out {self.holdout_sequences} of "
                             f"{len(self.sequences)} sequences: keep one for training")
        if self.trackers not in ("simulated", "exact"):
            raise ValueError(f"trackers must be 'simulated' or 'exact', got {self.trackers!r}")
        if self.tracker_noise.enabled and self.trackers != "simulated":
            raise ValueError("tracker_noise needs trackers='simulated'")
        if self.workers < 1 or self.supersample < 1:
            raise ValueError("workers and supersample must be at least 1")


def parse_sequences(text: str) -> tuple[tuple[str, ...], ...]:
    """'smile+grin,talk_calm' -> (('smile', 'grin'), ('talk_calm',))."""
    out = tuple(tuple(m.strip() for m in seq.split("+") if m.strip())
                for seq in text.split(",") if seq.strip())
    if not out:
        raise ValueError("no motions given")
    return out


def sequence_name(motions: Sequence[str]) -> str:
    return "-".join(motions)


def _to_u8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _parts_u8(parts: np.ndarray) -> np.ndarray:
    return (parts.astype(np.int16) + 1).astype(np.uint8)  # 0 = background, i + 1 = part i


def _holdout_cameras(spec: CaptureSpec, rig: list[RigCamera]) -> tuple[str, ...]:
    names = [c.name for c in rig]
    if spec.holdout_cameras is not None:
        unknown = [n for n in spec.holdout_cameras if n not in names]
        if unknown:
            raise ValueError(f"unknown held-out camera(s) {unknown}; the rig has {names}")
        return tuple(spec.holdout_cameras)
    return default_holdout(rig)


def default_holdout(rig: list[RigCamera]) -> tuple[str, ...]:
    """The default novel-view camera: never the front one, the camera at azimuth 0 (the
    training would not see the face straight on; with 4 cameras it is the only one that
    does). The front arc's cameras run left to right, evenly: an odd count has its centre
    camera at azimuth 0, and the one after it is held out; an even count has none there, and
    the first of the two nearest it is held out (the other trains). A rig of one camera holds
    none out."""
    if len(rig) < 2:
        return ()
    front = [c.name for c in rig if c.role == "front"]
    if len(front) % 2 == 1 and len(front) >= 3:
        return (front[len(front) // 2 + 1],)
    return (front[len(front) // 2],)


class _Bounds:
    def __init__(self) -> None:
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)

    def add(self, points: np.ndarray) -> None:
        self.lo = np.minimum(self.lo, points.min(axis=0))
        self.hi = np.maximum(self.hi, points.max(axis=0))

    def box(self, margin: float = 0.05) -> list[list[float]]:
        return [(self.lo - margin).tolist(), (self.hi + margin).tolist()]


def _film(actor: Actor, motions: Sequence[str], seq: str, spec: CaptureSpec,
          rig: list[RigCamera], writer: DatasetWriter, pool: ThreadPoolExecutor,
          rig_params, bounds: _Bounds, tick: Callable[[], None]) -> None:
    track = motion_sequence(list(motions))
    fps = spec.studio.fps
    frames = int(np.floor(track.duration * fps + 1e-9)) + 1
    if spec.max_frames is not None:
        frames = min(frames, spec.max_frames)

    def shoot(cam: RigCamera, f: int, posed) -> None:
        view: ActorView = actor.render(posed, cam.camera, background=spec.background,
                                       supersample=spec.supersample)
        writer.write_view(seq, f, cam.name, _to_u8(view.rgb), _to_u8(view.alpha),
                          _parts_u8(view.parts))

    per_frame = []
    for f in range(frames):
        params = track.sample(f / fps, rig_params)
        params["betas"] = np.asarray(actor.betas, dtype=np.float64)
        posed = actor.pose(params)
        bounds.add(posed.body_vertices)
        for job in [pool.submit(shoot, cam, f, posed) for cam in rig]:
            job.result()
            tick()
        per_frame.append(params)
    stacked = {k: np.stack([p[k] for p in per_frame]) for k in per_frame[0] if k != "betas"}
    stacked["betas"] = np.asarray(actor.betas, dtype=np.float64)
    info = None
    if spec.tracker_noise.enabled:
        info = {"tracker_noise": asdict(spec.tracker_noise)}
        buf = io.BytesIO()
        np.savez(buf, **stacked)
        write_atomic(true_params_path(writer.root, seq), buf.getvalue())
    if spec.trackers == "simulated":
        rng = np.random.default_rng([spec.seed, 2024, *seq.encode()])
        stacked = simulate_trackers(stacked, actor.model.data.hand_components, rng=rng,
                                    noise=spec.tracker_noise)
    writer.write_params(seq, stacked, info)


def _num_held(spec: CaptureSpec) -> int:
    return spec.holdout_sequences if len(spec.sequences) > 1 else 0


def count_views(spec: CaptureSpec) -> int:
    """How many images a capture renders (for progress bars)."""
    fps = spec.studio.fps
    n = 0
    k = _num_held(spec)
    held = spec.sequences[len(spec.sequences) - k:] if k else ()
    for motions in list(spec.sequences) + (list(held) if spec.cross_identity is not None
                                           else []):
        frames = int(np.floor(motion_sequence(list(motions)).duration * fps + 1e-9)) + 1
        n += min(frames, spec.max_frames or frames)
    return n * spec.num_cameras


def capture(out: str | Path, spec: CaptureSpec, *, model_dir: Path | None = None,
            progress: Progress | None = None) -> Path:
    """Film `spec` into the dataset folder `out` (which must not hold a dataset yet)."""
    files: BodyModelFiles = ensure_models(model_dir, seed=spec.seed)
    actor = Actor.load(files, spec.identity)
    config = replace(spec.studio, num_cameras=spec.num_cameras)
    rig = studio_rig(spec.resolution, config, seed=spec.seed)
    rig_params = model_rig(files, actor.model)
    holdout_cams = _holdout_cameras(spec, rig)
    names = [sequence_name(s) for s in spec.sequences]
    if len(set(names)) != len(names):
        raise ValueError(f"sequence names repeat: {names}")
    k = _num_held(spec)
    train_seqs, held_seqs = names[:len(names) - k], names[len(names) - k:]

    cameras = [CameraSpec.from_camera(c.name, c.camera, role=c.role) for c in rig]
    writer = DatasetWriter(
        out, name=f"synthetic-{actor.name}", fps=config.fps, cameras=cameras,
        part_names=list(SMPLX_PART_NAMES), upper_body_parts=list(UPPER_BODY_PARTS),
        subject={"identity": actor.name, "identity_index": spec.identity,
                 "betas": np.asarray(actor.betas).tolist()},
        body_model={"type": "smplx", "num_betas": int(len(actor.betas)),
                    "num_expression": int(actor.model.num_expression),
                    "source": f"synthetic-seed{spec.seed}", "hand_pca": None,
                    "flat_hand_mean": False, "trackers": spec.trackers},
        synthetic=True)
    total, done = count_views(spec), 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total)

    bounds = _Bounds()
    splits: dict[str, dict] = {
        "train": {"sequences": train_seqs,
                  "cameras": [c.name for c in rig if c.name not in holdout_cams]},
        "novel_view": {"sequences": train_seqs, "cameras": list(holdout_cams)},
        "self_reenactment": {"sequences": held_seqs, "cameras": [c.name for c in rig]},
    }
    with ThreadPoolExecutor(spec.workers) as pool:
        for motions, seq in zip(spec.sequences, names, strict=True):
            _film(actor, motions, seq, spec, rig, writer, pool, rig_params, bounds, tick)
        if spec.cross_identity is not None and held_seqs:
            other = Actor.load(files, spec.cross_identity)
            cross = []
            for motions, seq in zip(spec.sequences[len(names) - k:], held_seqs, strict=True):
                cross.append(f"cross-{other.name}-{seq}")
                _film(other, motions, cross[-1], spec, rig, writer, pool, rig_params, bounds,
                      tick)
            splits["cross_identity"] = {
                "sequences": cross, "cameras": [c.name for c in rig if c.role == "front"],
                "identity": other.name}
    writer.set_subject_bounds(bounds.box())
    writer.write_splits(splits)
    writer.close()
    return Path(out)
