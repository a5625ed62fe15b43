"""What each drive of the studio webcam protocol feeds the fit (`protocol.run_condition`).

A drive is the live path with some of its inputs swapped for the truth, or with another fit
configuration:

* ``live``: the tracked landmarks, today's fit;
* ``embedding``: the same landmarks through the learned landmark embedding and BlazePose's
  image z (the issue's "learned embedding + 3D cues"; the weight set on held-out renders,
  docs/tracking.md);
* ``arm_cues``: the same landmarks with BlazePose's world bone directions and the elbow
  hinge (`sequence.ARM_CUES`); ``embedding_arm_cues``: both;
* ``true_body``, ``true_body_face``, ``true_all``: the tracked 2D landmarks of those parts
  replaced by the truth (the part-attribution table);
* ``*_depth``: the depth question. The true camera depth of the body landmarks of one part
  (the arms' bones, or the torso: the shoulders' line and the nose against each shoulder)
  is given to the fit through its world term (`world_cues`), as if BlazePose's metric z were
  exact, on top of the tracked or the true 2D landmarks: what the remaining gap costs
  because a monocular 2D fit cannot tell near from far;
* ``arm_cues_corrected``: the arm cues on BlazePose's world arm bones through the learned
  correction (`track.fit.world_correction`); ``arm_cues_true_world``: on the true pose points
  in BlazePose's place (that correction's ceiling); ``arm_cues_true_forearms``,
  ``arm_cues_true_upper_arms``: only those bones' directions true;
  ``arm_cues_true_shoulders_2d``: only the shoulders' two 2D points true;
  ``arm_cues_true_torso_axis``: BlazePose's world hips moved so that its torso axis is the
  truth's, its shoulders kept, and the axis used in every frame (hips in view or not): what
  a lean cue that follows the body would buy; ``arm_cues_true_torso``: the shoulders' line
  from the truth as well (at its own turn: no gain), each arm bone kept at BlazePose's
  direction and length from its moved shoulder: what a cue for the torso's whole orientation
  would buy.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from avatar_core.track.fit.sequence import with_arm_cues
from avatar_core.track.fit.world_correction import bone_directions, with_bone_directions
from avatar_core.track.fit.world_cues import DEPTH_PAIRS, WORLD_TO_CAMERA, torso_axis

ALL_PARTS = ("pose", "face", "left_hand", "right_hand")
# BlazePose pairs (landmark, reference) of each part whose true depth a drive may give.
DEPTH_PARTS = {"arms": DEPTH_PAIRS[:4], "torso": DEPTH_PAIRS[4:]}
# The world term's weight for a true depth: a pose landmark's 2D weight (`GROUP_WEIGHT`).
TRUE_DEPTH_WEIGHT = 2.0
# The embedding drive's image-z weight: set on identity 1's held-out frames (docs/results.md).
EMBEDDING_IMAGE_Z_WEIGHT = 0.1


@dataclass(frozen=True)
class Drive:
    label: str
    true_2d: tuple[str, ...] = ()         # landmark groups whose 2D comes from the truth
    true_depth: tuple[str, ...] = ()      # `DEPTH_PARTS` whose depth comes from the truth
    embedding: bool = False               # the learned landmark embedding + image z
    pose_hands: bool | None = None        # `SequenceFitConfig.pose_hands`; None: as given
    arm_cues: bool = False                # `sequence.ARM_CUES`
    true_world: bool = False              # BlazePose's world landmarks replaced by the truth
    # ARM_BONES indices whose world direction alone comes from the truth (each rebuilt on
    # BlazePose's own near end at its own length; the other bones BlazePose's)
    true_bones: tuple[int, ...] = ()
    true_pose_rows: tuple[int, ...] = ()  # BlazePose rows whose 2D alone comes from the truth
    world_correction: bool = False        # BlazePose's world arm bones corrected (the asset)
    true_torso_axis: bool = False         # BlazePose's torso axis from the truth, always used
    true_shoulder_line: bool = False      # BlazePose's shoulders' line from the truth


DRIVES = {
    "live": Drive("webcam, live fit"),
    "embedding": Drive("webcam, learned embedding + 3D cues", embedding=True),
    "arm_cues": Drive("webcam, world bone directions + elbow hinge", arm_cues=True),
    "embedding_arm_cues": Drive("webcam, learned embedding + world bones + elbow hinge",
                                embedding=True, arm_cues=True),
    "live_pose_hands": Drive("webcam, live fit + the pose's hand points", pose_hands=True),
    "arm_cues_true_world": Drive("webcam + world bones and elbow hinge from true world "
                                 "landmarks", arm_cues=True, true_world=True),
    "arm_cues_corrected": Drive("webcam, world bones corrected + elbow hinge", arm_cues=True,
                                world_correction=True),
    "arm_cues_true_upper_arms": Drive("webcam + world bones, the upper arms' from the truth",
                                      arm_cues=True, true_bones=(0, 2)),
    "arm_cues_true_forearms": Drive("webcam + world bones, the forearms' from the truth",
                                    arm_cues=True, true_bones=(1, 3)),
    "arm_cues_true_shoulders_2d": Drive("webcam + world bones, the shoulders' 2D from the "
                                        "truth", arm_cues=True, true_pose_rows=(11, 12)),
    "arm_cues_true_torso_axis": Drive("webcam + world bones, the torso's axis from the truth",
                                      arm_cues=True, true_torso_axis=True),
    "arm_cues_true_torso": Drive("webcam + world bones, the torso's axis and shoulders' line "
                                 "from the truth", arm_cues=True, true_torso_axis=True,
                                 true_shoulder_line=True),
    "true_body": Drive("true body 2D", ("pose",)),
    "true_body_face": Drive("true body + face 2D", ("pose", "face")),
    "true_all": Drive("all 2D true", ALL_PARTS),
    "live_true_depth": Drive("live 2D + true arm and torso depth",
                             true_depth=tuple(DEPTH_PARTS)),
    "true_all_arm_depth": Drive("all 2D true + true arm depth", ALL_PARTS, ("arms",)),
    "true_all_torso_depth": Drive("all 2D true + true torso depth", ALL_PARTS, ("torso",)),
    "true_all_depth": Drive("all 2D true + true arm and torso depth", ALL_PARTS,
                            tuple(DEPTH_PARTS)),
}
DEFAULT_DRIVES = ("live", "embedding", "true_body", "true_body_face", "true_all")
DRIVE_LABELS = {"true": "true parameters", **{k: d.label for k, d in DRIVES.items()}}


def check_drives(drives) -> None:
    unknown = [d for d in drives if d not in DRIVES]
    if unknown or not drives:
        raise ValueError(f"drives must be among {', '.join(DRIVES)}, got {list(drives)}")


def drive_config(name: str, base, embedding=None):
    """`base` (a SequenceFitConfig) as drive `name` fits: the embedding and its image z, or
    the world term that carries a true depth; `embedding`: the one to load (default: the
    committed asset)."""
    drive = DRIVES[name]
    fit = base.fit
    if drive.embedding:
        from avatar_core.track.fit.embedding import load_embedding

        fit = dataclasses.replace(fit, embedding=embedding or load_embedding(),
                                  image_z_weight=EMBEDDING_IMAGE_Z_WEIGHT)
    if drive.true_depth:
        fit = dataclasses.replace(fit, world_weight=TRUE_DEPTH_WEIGHT, embedding=None)
    pose_hands = base.pose_hands if drive.pose_hands is None else drive.pose_hands
    out = dataclasses.replace(base, fit=fit, pose_hands=pose_hands)
    if drive.world_correction:
        from avatar_core.track.fit.world_correction import load_world_correction

        out = dataclasses.replace(out, world_correction=load_world_correction())
    out = with_arm_cues(out) if drive.arm_cues else out
    if drive.true_torso_axis:
        out = dataclasses.replace(out, fit=dataclasses.replace(
            out.fit, torso_axis_hips_in_view=False))
    if drive.true_shoulder_line:
        out = dataclasses.replace(out, fit=dataclasses.replace(out.fit,
                                                               shoulder_line_yaw_gain=1.0))
    return out


def with_shoulder_line(world: np.ndarray, line: np.ndarray) -> np.ndarray:
    """[33, 3] BlazePose world landmarks with both shoulders moved about their midpoint, at
    their own width, so that the right shoulder to the left points along `line` (unit,
    BlazePose's axes); each arm bone then starts at its moved shoulder with BlazePose's own
    direction and length. Unchanged where a shoulder is missing."""
    out = np.array(world, dtype=np.float64)
    mid, width = out[[11, 12]].mean(axis=0), float(np.linalg.norm(out[11] - out[12]))
    if not (np.isfinite(width) and width > 1e-6):
        return out
    unit, length = bone_directions(out * WORLD_TO_CAMERA)
    half = width / 2 * np.asarray(line, dtype=np.float64)
    out[11], out[12] = mid + half, mid - half
    return with_bone_directions(out, unit, length)


def with_torso_axis(world: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """[33, 3] BlazePose world landmarks with both hips moved so that the hips' midpoint to
    the shoulders' points along `axis` (unit, BlazePose's axes), at BlazePose's own length and
    hip width (0.3 m and 0.2 m where its hips are missing)."""
    out = np.array(world, dtype=np.float64)
    half = (out[23] - out[24]) / 2
    length = float(np.linalg.norm(torso_axis(out)))
    if not (np.isfinite(length) and length > 1e-3 and np.all(np.isfinite(half))):
        length, half = 0.3, np.array([0.1, 0.0, 0.0])
    mid = out[[11, 12]].mean(axis=0) - length * np.asarray(axis, dtype=np.float64)
    out[23], out[24] = mid + half, mid - half
    return out


def true_world(model_points: np.ndarray, parts) -> np.ndarray:
    """[33, 3] BlazePose-layout world landmarks whose z is the true camera depth (m, away from
    the camera) of the pose rows in the pairs of `parts`; NaN elsewhere (those pairs drop).
    `model_points`: the fitter's pose rows [33, 3] in the model frame (the camera's)."""
    out = np.full((len(model_points), 3), np.nan)
    rows = sorted({i for part in parts for pair in DEPTH_PARTS[part] for i in pair})
    out[rows, 2] = -model_points[rows, 2]
    return out
