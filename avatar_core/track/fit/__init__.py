"""Fitting: tracked landmarks -> SMPL-X parameters (face, hands, upper body), per frame.

`correspondence` maps MediaPipe's landmark layouts onto the body model's keypoints,
`keypoints` computes those keypoints for a parameter set, `camera` is the webcam's pinhole,
`fitter` optimizes one frame, `one_euro` smooths, and `sequence` (`SequenceFit`) runs a stream
of frames with warm starts, smoothing and the hold-then-relax policy for lost tracks. `gaze`
turns the eyes of a fitted body onto the tracked iris centres.
"""
