"""Enrollment jobs: one uploaded video -> a drivable avatar (avatar_core/enroll).

Submitting (:func:`enroll_config`, :func:`video_limits`, :func:`refusal_status`): the config is
resolved and capped by the server's settings, and the video probed (avatar_core/enroll/video.py)
before a job row exists, so a refused video leaves nothing behind. Running
(:func:`run_enrollment`, called by server/jobs/run.py for a job of kind ``enroll``): decode
within the stored limits, enroll with progress events like a training job's, and leave the
package where the worker registers it (``out/avatar``). A video the pipeline refuses (no
person, never turns, too dark, ...) fails the job with the reason and what to do, and the
video is deleted.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from avatar_core.enroll.config import EnrollConfig
from avatar_core.enroll.errors import EnrollmentRefused
from avatar_core.enroll.video import VideoLimits

__all__ = ["ENROLL_PRESET", "PROGRESS_STEPS", "VIDEO_FILE", "EnrollCaps", "enroll_config",
           "refusal_status", "run_enrollment", "video_limits"]

log = logging.getLogger(__name__)

ENROLL_PRESET = "enroll"
PROGRESS_STEPS = 1000  # an enrollment's progress counts thousandths: iteration / total
VIDEO_FILE = "video"   # jobs/<id>/dataset/video<suffix>
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".webm", ".mkv")
# Refusals about size answer 413 (as every other upload past a limit); the rest 422.
TOO_LARGE = ("file_too_large", "too_long", "too_many_frames", "resolution_too_large")


@dataclasses.dataclass(frozen=True)
class EnrollCaps:
    """The most an enrollment job may ask (settings ``enroll_max_*``)."""

    max_iterations: int = 30_000
    max_resolution: int = 1024
    max_fit_iterations: int = 5_000


def video_limits(settings: Any) -> VideoLimits:
    """The server's ``enroll_*`` settings as VideoLimits (defaults for absent ones)."""
    default = VideoLimits()
    names = {"max_bytes": "enroll_max_video_bytes"}
    return VideoLimits(**{f.name: getattr(settings, names.get(f.name, f"enroll_{f.name}"),
                                          getattr(default, f.name))
                          for f in dataclasses.fields(VideoLimits)})


def enroll_caps(settings: Any) -> EnrollCaps:
    default = EnrollCaps()
    return EnrollCaps(**{f.name: getattr(settings, f"enroll_{f.name}", getattr(default, f.name))
                         for f in dataclasses.fields(EnrollCaps)})


class ConfigRefused(ValueError):
    """A bad enrollment config; the message names the key (HTTP 422)."""


def enroll_config(value: Any, caps: EnrollCaps) -> EnrollConfig:
    """``None`` or ``"enroll"``: the defaults; an object: EnrollConfig fields (and optionally
    ``"preset": "enroll"``). ConfigRefused naming the key otherwise, and past ``caps``."""
    if value is None or value == ENROLL_PRESET:
        config = EnrollConfig()
    elif isinstance(value, dict):
        fields = dict(value)
        preset = fields.pop("preset", ENROLL_PRESET)
        if preset != ENROLL_PRESET:
            raise ConfigRefused(f"a video trains with the preset {ENROLL_PRESET!r}, not "
                                f"{preset!r}")
        known = {f.name for f in dataclasses.fields(EnrollConfig)}
        unknown = sorted(set(fields) - known)
        if unknown:
            raise ConfigRefused(f"unknown enrollment config key {unknown[0]!r} (known: "
                                f"{', '.join(sorted(known))})")
        for key, val in fields.items():
            kind = type(getattr(EnrollConfig, key, None))
            if isinstance(val, bool) != (kind is bool) or not isinstance(val, int | float):
                raise ConfigRefused(f"enrollment config {key!r} must be a "
                                    f"{'boolean' if kind is bool else 'number'}")
            if kind is int and not (isinstance(val, int) or float(val).is_integer()):
                raise ConfigRefused(f"enrollment config {key!r} must be a whole number")
            fields[key] = kind(val)
        try:
            config = EnrollConfig(**fields)
        except ValueError as exc:
            raise ConfigRefused(str(exc)) from None
    else:
        raise ConfigRefused(f"a video's config is the preset {ENROLL_PRESET!r} or an object of "
                            "EnrollConfig fields")
    for key, cap in (("iterations", caps.max_iterations), ("resolution", caps.max_resolution),
                     ("track_size", caps.max_resolution),
                     ("fit_iterations", caps.max_fit_iterations)):
        if getattr(config, key) > cap:
            raise ConfigRefused(f"enrollment config {key!r} is {getattr(config, key)}, more "
                                f"than this server's {cap}")
    return config


def decode_side(config: EnrollConfig) -> int:
    """The longer side frames are decoded at: what the tracker looks at (``track_size``) and
    what training uses (``resolution``), whichever is larger (a 64 px training run still
    tracks at 256 px: people are not found in 64 px frames)."""
    return max(config.resolution, config.track_size)


def refusal_status(refused: EnrollmentRefused) -> int:
    return 413 if refused.reason in TOO_LARGE else 422


def video_suffix(filename: str | None) -> str:
    """The uploaded file's suffix when it is a known video one (only for people reading the
    folder: PyAV reads the container from the bytes), else none."""
    suffix = Path(filename or "").suffix.lower()
    return suffix if suffix in VIDEO_SUFFIXES else ""


def job_config(config: EnrollConfig, limits: VideoLimits) -> dict[str, Any]:
    """What the job row stores (and JobOut shows): the preset, the config, the limits the job
    decodes within."""
    return {"preset": ENROLL_PRESET, **dataclasses.asdict(config),
            "video_limits": dataclasses.asdict(limits)}


def _from_job_config(stored: dict[str, Any]) -> tuple[EnrollConfig, VideoLimits]:
    fields = {k: v for k, v in stored.items() if k not in ("preset", "video_limits")}
    return EnrollConfig(**fields), VideoLimits(**stored.get("video_limits", {}))


# Where each stage of avatar_core/enroll (which reports each stage's own 0..1) lies in the
# job's progress; training takes most of the time. A stage not named here keeps the bar where
# it is.
STAGE_SPANS = {"decode": (0.0, 0.03), "select": (0.03, 0.05), "preflight": (0.05, 0.08),
               "track": (0.08, 0.30), "fit": (0.30, 0.38), "dataset": (0.38, 0.40),
               "train": (0.40, 0.99), "done": (0.99, 1.0)}


class _Progress:
    """``progress(stage, fraction)`` as job events: ``progress`` events counting
    ``PROGRESS_STEPS`` steps over the whole enrollment, with the ``stage`` and its own
    ``stage_progress``; written when the step or the stage changes (a pipeline may call it
    per frame or per iteration: the store gets at most ~1000 writes). ``check()`` runs at
    each call (cancel and stop requests)."""

    def __init__(self, report: Callable[[dict[str, Any]], None], check: Callable[[], None]):
        self.report, self.check = report, check
        self.last: tuple[str, int] | None = None
        self.step = 0

    def __call__(self, stage: str, fraction: float) -> None:
        fraction = min(1.0, max(0.0, float(fraction)))
        start, end = STAGE_SPANS.get(stage, (self.step / PROGRESS_STEPS,) * 2)
        self.step = max(self.step, round((start + (end - start) * fraction) * PROGRESS_STEPS))
        if (stage, self.step) != self.last:
            self.last = (stage, self.step)
            self.report({"type": "progress", "iteration": self.step, "total": PROGRESS_STEPS,
                         "stage": str(stage)[:64], "stage_progress": round(fraction, 4)})
        self.check()


def run_enrollment(job: Any, job_dir: Path, out: Path, report: Callable[[dict], None],
                   check: Callable[[], None], set_error: Callable[[str], None],
                   body_models: str | None = None) -> bool:
    """Enroll the job's video into ``out/avatar``; True when done, False when the video was
    refused (the reason is set and the video deleted). ``check`` raises to stop (a cancel,
    the server stopping)."""
    from avatar_core.enroll import enroll
    from avatar_core.enroll.video import read_video

    config, limits = _from_job_config(job.config)
    dataset = Path(job.dataset_path)
    videos = sorted(dataset.glob(f"{VIDEO_FILE}*"))
    if not videos:
        set_error("the job's video is no longer on the server")
        return False
    out.parent.mkdir(parents=True, exist_ok=True)
    progress = _Progress(report, check)
    try:
        progress("decode", 0.0)
        video = read_video(videos[0], limits, long_side=decode_side(config))
        progress("decode", 1.0)
        if out.exists():  # an earlier attempt's leftovers: enrollment starts over
            shutil.rmtree(out)
        out.mkdir(parents=True)
        result = enroll(list(video.frames), video.fps, out, config=config,
                        focal_px=video.focal_px, progress=progress, body_models=body_models)
    except EnrollmentRefused as refused:
        log.info("job %s: video refused: %s", job.id, refused.reason)
        set_error(f"{refused.message} {refused.what_to_do}".strip())
        report({"type": "error", "message": str(refused), **refused.to_dict()})
        shutil.rmtree(dataset, ignore_errors=True)  # nothing of a refused video is kept
        return False
    package = Path(result.package)
    if package.resolve() != (out / "avatar").resolve():
        package.rename(out / "avatar")
    shutil.rmtree(out / "dataset", ignore_errors=True)  # the frames written for training
    summary = result.to_dict()
    report({"type": "message", "message": "enrolled", "frames": summary.get("frames"),
            "focal_source": summary.get("focal_source")})
    return True
