"""Training losses and evaluation metrics for rendered avatars.

* ``image``: ``l1``, ``psnr``, ``ssim`` (scikit-image's Gaussian SSIM), ``dssim_loss`` and
  3DGS's ``photometric_loss``; masked and differentiable.
* ``perceptual``: ``lpips_metric`` (None unless LPIPS can run offline).
* ``keypoints``: AKD per group (face, hands, torso) from posed bodies and a camera.
* ``temporal``: temporal jitter error of image sequences and keypoint tracks.
"""

from .image import dssim_loss, l1, photometric_loss, psnr, ssim, ssim_map
from .keypoints import (
    akd,
    body_akd,
    body_keypoints,
    keypoint_groups,
    project_keypoints,
)
from .perceptual import lpips_metric
from .temporal import keypoint_tje, tje

__all__ = [
    "akd", "body_akd", "body_keypoints", "dssim_loss", "keypoint_groups", "keypoint_tje", "l1",
    "lpips_metric", "photometric_loss", "project_keypoints", "psnr", "ssim", "ssim_map", "tje",
]
