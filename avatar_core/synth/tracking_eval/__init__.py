"""Tracking on renders with known parameters: the real Tracker + SequenceFit on the textured
synthetic actor, against the SMPL-X parameters that posed it.

Each clip of the motion library is played on identity 0 of the synthetic family (the
capture studio's `Actor`: textured, hair, collar), placed in front of a 640x480 pinhole webcam
(60 deg horizontal field of view, at the model-space origin looking down -z: the fitter's own
camera model) framing head to waist, over a static noisy background with per-frame sensor
noise. The frames go, in order, through `Tracker` (tracking mode, one ONNX thread) and one
`SequenceFit` per clip (warm starts; the fit's own One Euro smoothing gives the smoothed
output, its unsmoothed composition the raw one). The fitter is given the true betas.

Reported per clip and overall:

* detection rate per group: face and pose over all frames, each hand over the frames in which
  all its 21 true keypoints are inside the image;
* parameter recovery (frames where the group was detected): head rotation in the world and
  the jaw rotation (geodesic, deg); the expression-driven landmark error: the 51 static face
  landmarks in the head's frame (so head pose is factored out), fitted vs true, in mm, next to
  how far the true expression moved them from the neutral face; elbow flexion difference and
  wrist rotation in the world (deg); finger joints (mean geodesic over 15 joints, deg) next to
  the error of simply keeping the model's mean hand;
* AKD (px) of face (51 static landmarks), each hand (wrist, 15 finger joints, 5 tips) and torso
  (12 upper-body joints, `avatar_core.metrics.keypoints`), fitted vs true parameters, same
  camera, over the frames where that group was detected;
* keypoint TJE (px, `keypoint_tje`) of all those keypoints over the clip, without and with the
  fit's One Euro smoothing;
* tracking + fitting time per frame (render time excluded).

The command line is `bench/track_eval.py`; the tracking benches and tests/test_track_synthetic.py
use the scene and `run_clip` from here.
"""

from .metrics import (
    GROUPS,
    HAND_SIDES,
    LH,
    NUM_FACE_HANDS,
    RH,
    TJE_SKIP_S,
    Posed,
    aa_to_matrix,
    clip_metrics,
    evaluate_params,
    geodesic_deg,
)
from .report import contact_sheet, draw_fit, offset_table, overall, tables
from .run import IGNORABLE, ClipResult, make_tracker_and_fit, run_clip
from .scene import (
    CLIPS,
    FOV_X_DEG,
    HEIGHT,
    WIDTH,
    Scene,
    background,
    clip_params,
    make_scene,
    render_frame,
    subject_transl,
    webcam_camera,
)

__all__ = ["CLIPS", "FOV_X_DEG", "GROUPS", "HAND_SIDES", "HEIGHT", "IGNORABLE", "LH",
           "NUM_FACE_HANDS", "RH", "TJE_SKIP_S", "WIDTH", "ClipResult", "Posed", "Scene",
           "aa_to_matrix", "background", "clip_metrics", "clip_params", "contact_sheet",
           "draw_fit", "evaluate_params", "geodesic_deg", "make_scene",
           "make_tracker_and_fit", "offset_table", "overall", "render_frame", "run_clip",
           "subject_transl", "tables", "webcam_camera"]
