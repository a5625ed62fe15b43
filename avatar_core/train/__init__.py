"""Training an avatar on a multi-view dataset.

The loop is :class:`trainer.Trainer` (``telesplat train``), configured by :mod:`config`
(JSON/TOML). It calls: :mod:`data` (training views, weight maps, subject crops, fused
per-frame parameters), :mod:`posing` (body model, fine-tuned deltas, world Gaussians,
initial colours), :mod:`photometric` (the fused L1 + D-SSIM loss), :mod:`optim` (learning
rates and Adam groups), :mod:`density` (adaptive density control with Adam-state surgery),
:mod:`regularizers` (GaussianAvatars' local-frame hinges) and :mod:`checkpoint`.
"""
