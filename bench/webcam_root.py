"""Where a webcam-driven avatar's root goes wrong (issue 28): `telesplat eval --protocol
webcam` on a trained avatar, once per fit variant, with the root's error split along the
webcam's own axes, the true and fitted root in the webcam's frame, and BlazePose's world torso
axis (the hips' midpoint to the shoulders') against the true one. With `--recordings`, only
that axis and the shoulders' line's turn, on the studio protocol's recordings
(bench/webcam_replay.py --record, --turns for a turned body). With `--runs`, the root's
error split the same way on replayed runs (bench/webcam_replay.py --replay's runs.pkl).

    ARMS="(11,13),(13,15),(12,14),(14,16),(12,11)"
    OMP_NUM_THREADS=1 PYTHONPATH=. python bench/webcam_root.py \
        out/e28/work/finetune_fixed/avatar_final out/e28/noisy_data \
        --variants "torso:fit.world_direction_bones=($ARMS,((23,24),(11,12)))"
    PYTHONPATH=. python bench/webcam_root.py --recordings /tmp/w28/rec
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from webcam_replay import parse_variants  # noqa: E402

from avatar_core.body.skeleton import JOINT  # noqa: E402
from avatar_core.metrics import webcam as W  # noqa: E402
from avatar_core.synth.tracking_eval.protocol import with_variant  # noqa: E402
from avatar_core.track.fit.sequence import live_config  # noqa: E402
from avatar_core.track.fit.world_cues import (  # noqa: E402
    SHOULDER_LINE,
    TORSO_AXIS,
    WORLD_TO_CAMERA,
    torso_axis,
)

HIPS, SHOULDERS = TORSO_AXIS[0]  # BlazePose's landmarks at either end of the axis
RIGHT_SHOULDER, LEFT_SHOULDER = SHOULDER_LINE[0]


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    return float(np.degrees(np.arccos(np.clip(u @ v, -1.0, 1.0))))


def root_in_webcam(global_orient: np.ndarray, cam) -> np.ndarray:
    """A root (rotation vector in the studio's world) in the webcam's frame as the fit
    states it (x right, y up, z toward the camera), as a rotation vector in degrees."""
    return np.degrees(W.webcam_orient(global_orient, cam))


def root_error_axes(fit: dict, truth: dict, cam) -> np.ndarray:
    """[3] the root's error (fit after truth, degrees) about the webcam's x (right: a lean
    toward or away from it), y (down: a turn) and z (the optical axis: a roll)."""
    err = W.world_rotations(fit)[0] @ W.world_rotations(truth)[0].T   # the studio's frame
    return np.degrees(Rotation.from_matrix(cam.R @ err @ cam.R.T).as_rotvec())


def torso_axis_error(frame: W.WebcamFrame, body_model) -> float | None:
    """BlazePose's world torso axis against the true one (the body model's hip and shoulder
    joints in the webcam's frame), degrees; None when a hip or shoulder is not seen."""
    seen = seen_torso_axis(frame.observations.world)
    if seen is None:
        return None
    out = body_model({k: np.asarray(v)[None] for k, v in frame.truth.items()})
    joints = np.asarray(out.joints[0].detach().cpu().numpy(), dtype=np.float64)
    mid = lambda names: joints[[JOINT[n] for n in names]].mean(0)  # noqa: E731
    true = frame.camera.R @ (mid(("left_shoulder", "right_shoulder"))
                             - mid(("left_hip", "right_hip")))
    return angle_deg(seen, W.OPENCV_FROM_MODEL @ true)


def seen_torso_axis(world: np.ndarray | None) -> np.ndarray | None:
    """[3] BlazePose's torso axis in the fit's camera frame; None when a hip or shoulder has
    no world point."""
    if world is None or not np.isfinite(world[[*HIPS, *SHOULDERS]]).all():
        return None
    return torso_axis(world) * WORLD_TO_CAMERA


def line_turn_deg(world: np.ndarray) -> float:
    """The shoulders' line's turn about the vertical (deg) in [33, 3] points in the fit's
    camera frame (0: square to the camera)."""
    line = world[LEFT_SHOULDER] - world[RIGHT_SHOULDER]
    return float(np.degrees(np.arctan2(line[2], line[0])))


def recordings_torso(folder: Path) -> None:
    """BlazePose's world torso axis and shoulders' line against the true pose points, per
    recording."""
    import pickle

    print("| recording | frames with both hips seen | torso axis error median / p90 deg | "
          "lean toward the camera, median deg: BlazePose / true | shoulders' line turn, "
          "median deg: BlazePose / true (ratio) |")
    print("|---" * 5 + "|")
    for path in sorted(folder.glob("*.pkl")):
        with open(path, "rb") as f:
            rec = pickle.load(f)
        errors, leans, turns = [], [], []
        for obs, true_points in zip(rec.live, rec.true_points, strict=True):
            true_points = np.asarray(true_points)
            if obs.world is not None and np.isfinite(obs.world[[*SHOULDERS]]).all():
                turns.append([line_turn_deg(obs.world * WORLD_TO_CAMERA),
                              line_turn_deg(true_points)])
            seen = seen_torso_axis(obs.world)  # the fit's frame, as true_points
            if seen is None:
                continue
            true = torso_axis(true_points)
            errors.append(angle_deg(seen, true))
            leans.append([np.degrees(np.arctan2(v[2], v[1])) for v in (seen, true)])
        turn = np.median(turns, axis=0) if turns else (np.nan, np.nan)
        ratio = f"{turn[0] / turn[1]:.2f}" if abs(turn[1]) > 1.0 else "-"
        turn_text = f"{turn[0]:+.1f} / {turn[1]:+.1f} ({ratio})"
        if not errors:
            print(f"| {path.stem} | 0 of {len(rec.live)} | - | - | {turn_text} |")
            continue
        lean = np.median(leans, axis=0)
        print(f"| {path.stem} | {len(errors)} of {len(rec.live)} | {np.median(errors):.1f} / "
              f"{np.percentile(errors, 90):.1f} | {lean[0]:+.1f} / {lean[1]:+.1f} | "
              f"{turn_text} |")


def runs_root(paths: list[Path]) -> None:
    """The root's error along the webcam's axes per condition and drive of replayed runs
    (bench/webcam_replay.py --replay's runs.pkl): the protocol's webcam is the fit's frame."""
    from avatar_core.synth.tracking_eval.protocol import webcam_camera
    from avatar_core.synth.tracking_eval.protocol_report import load_runs

    cam = webcam_camera()
    print("| condition | drive | root error about the webcam's x (lean) / y (turn) / z (roll), "
          "mean deg | root error, mean deg |")
    print("|---" * 4 + "|")
    for run in load_runs(paths):
        for drive, fits in run.smooth.items():
            axes = np.array([root_error_axes(fit, truth, cam)
                             for fit, truth in zip(fits, run.truth, strict=True)])
            mean = " / ".join(f"{x:+.1f}" for x in axes.mean(0))
            print(f"| {run.condition.name} | {drive} | {mean} | "
                  f"{np.linalg.norm(axes, axis=1).mean():.1f} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("avatar", nargs="?")
    ap.add_argument("dataset", nargs="?")
    ap.add_argument("--recordings", type=Path, help="the studio protocol's recordings only")
    ap.add_argument("--runs", type=Path, nargs="+",
                    help="only the root's error split, on bench/webcam_replay.py's runs.pkl")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--variants", default="", help="as bench/webcam_replay.py's: "
                    "'label:fit.field=value;...' over the live configuration")
    args = ap.parse_args()
    if args.recordings:
        recordings_torso(args.recordings)
        return 0
    if args.runs:
        runs_root(args.runs)
        return 0
    if not (args.avatar and args.dataset):
        ap.error("an avatar and a dataset, or --recordings")
    dataset = W.load_dataset(args.dataset)
    avatar = W.load_avatar(args.avatar)
    print("| fit | PSNR dB | with the true root dB | root deg | root error about the webcam's "
          "x / y / z, mean deg | true root in the webcam frame | fitted root in the webcam "
          "frame | BlazePose's torso axis against the truth, median deg |")
    print("|---" * 8 + "|")
    for label, changes in parse_variants(args.variants).items():
        frames: list[W.WebcamFrame] = []
        fit = with_variant(live_config(), changes).fit
        res = W.evaluate_webcam(avatar, dataset, size=args.size, max_frames=args.max_frames,
                                fit_config=fit, on_frame=frames.append)
        axes = np.array([root_error_axes(f.webcam, f.truth, f.camera) for f in frames])
        true_root = np.array([root_in_webcam(f.truth["global_orient"], f.camera)
                              for f in frames])
        fit_root = np.array([root_in_webcam(f.webcam["global_orient"], f.camera)
                             for f in frames])
        torso = [e for f in frames
                 if (e := torso_axis_error(f, avatar.animator.body_model)) is not None]
        webcam, true_root_drive = res.drives["webcam"], res.drives["webcam_true_root"]
        vec = lambda a: " / ".join(f"{x:+.1f}" for x in a.mean(0))  # noqa: E731
        torso_text = f"{np.median(torso):.1f} of {len(torso)} frames" if torso else "-"
        print(f"| {label or 'live'} | {webcam['psnr']:.2f} | {true_root_drive['psnr']:.2f} | "
              f"{webcam['deg_root']:.1f} | {vec(axes)} | {vec(true_root)} | {vec(fit_root)} | "
              f"{torso_text} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
