"""Build the world-landmark correction (`track.fit.world_correction`) from studio renders.

Each training condition (an identity of a synthetic family with more identities than the
protocol's two, filmed in one framing, playing motions the protocol never plays) is rendered,
tracked by the live tracker and paired with the true pose points
(`tracking_eval.protocol.record_condition`). The correction is solved on those pairs, the
mirror image of each frame included. Deterministic: the renders' noise is seeded per identity
and framing, and the same spec gives the same asset.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from avatar_core.synth.model_writer import synthetic_family
from avatar_core.track.fit import world_correction as wc

# Motions with arms at work that the protocol's take (`protocol.TAKE`) does not play, so the
# protocol scores the correction on motions it never saw.
TRAIN_TAKE = ("heart", "thumbs_up", "shrug", "fingertips_pushing", "peace", "letter_L",
              "number_1")
TRAIN_IDENTITIES = (1, 2, 3, 4)     # identity 0 is held out, as in the protocol's tuning
TRAIN_FRAMINGS = ("head_shoulders", "waist_up", "hips_in_view")


@dataclass(frozen=True)
class CorrectionSpec:
    identities: tuple[int, ...] = TRAIN_IDENTITIES  # of a family of max + 1 identities
    framings: tuple[str, ...] = TRAIN_FRAMINGS
    take: tuple[str, ...] = TRAIN_TAKE
    fps: float = 10.0
    max_frames: int | None = None
    ridge: float = wc.DEFAULT_RIDGE

    def recording_key(self) -> str:
        """What a recording depends on beyond its identity and framing (the renders' noise is
        seeded by those two), hashed: a work folder reused with another take is not read."""
        text = json.dumps([list(self.take), self.fps, self.max_frames])
        return hashlib.sha256(text.encode()).hexdigest()[:10]


def record_training(spec: CorrectionSpec, work: Path, model_dir: Path | None = None,
                    progress: Callable[[str, int, int], None] | None = None) -> list[Path]:
    """One recording per (identity, framing), pickled under `work` and named with the spec's
    `recording_key` (kept: re-solving with another ridge needs no new renders)."""
    import pickle

    from avatar_core.synth.tracking_eval.protocol import Condition, record_condition

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    models = None
    paths = []
    for identity in spec.identities:
        for framing in spec.framings:
            condition = Condition(identity, framing)
            path = work / f"{condition.name}_{spec.recording_key()}.pkl"
            if not path.exists():
                models = models or synthetic_family(max(spec.identities) + 1, model_dir)
                rec = record_condition(condition, spec.fps,
                                       max_frames=spec.max_frames, model_dir=models,
                                       take=spec.take, progress=progress)
                tmp = path.with_suffix(".tmp")
                with open(tmp, "wb") as f:
                    pickle.dump(rec, f)
                tmp.replace(path)
            paths.append(path)
    return paths


def pairs_of(recordings: Sequence) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(features [M, F], targets [M, 3 * bones], mask [M, bones]) over every frame of the
    recordings and its mirror image."""
    feats, targets, masks = [], [], []
    for rec in recordings:
        for obs, points in zip(rec.live, rec.true_points, strict=True):
            for mirror in (False, True):
                x, y, m = wc.training_pair(obs, np.asarray(points), mirror=mirror)
                if m.any():
                    feats.append(x)
                    targets.append(y)
                    masks.append(m)
    if not feats:
        raise ValueError("no frame with an arm bone seen: nothing to fit")
    return np.stack(feats), np.stack(targets), np.stack(masks)


def build_world_correction(spec: CorrectionSpec, work: Path, model_dir: Path | None = None,
                           progress: Callable[[str, int, int], None] | None = None
                           ) -> tuple[wc.WorldCorrection, dict]:
    """Record (or reuse) the training conditions and solve the correction; (correction,
    report with the training fit's bone errors before and after)."""
    import pickle

    paths = record_training(spec, work, model_dir, progress)
    recordings = []
    for path in paths:
        with open(path, "rb") as f:
            recordings.append(pickle.load(f))
    x, y, mask = pairs_of(recordings)
    corr = wc.solve(x, y, mask, ridge=spec.ridge)
    before, after = wc.bone_errors_deg(recordings, None), wc.bone_errors_deg(recordings, corr)
    report = {"spec": asdict(spec), "frames": int(len(x)),
              "train_bone_error_deg": {"blazepose": before, "corrected": after}}
    return corr, report


def write_asset(corr: wc.WorldCorrection, report: dict, out: Path) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    wc.save(corr, out)
    out.with_suffix(".json").write_text(json.dumps(report, indent=1, default=float) + "\n")
    return out
