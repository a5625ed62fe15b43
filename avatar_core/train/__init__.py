"""The optimisation core of the avatar trainer: learning rates and Adam groups (:mod:`optim`),
adaptive density control with Adam-state surgery (:mod:`density`) and the local-frame
regularisers of GaussianAvatars (:mod:`regularizers`). The training loop itself lives
elsewhere; these are the pieces it calls."""
