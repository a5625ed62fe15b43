"""The fitter's whole residual Jacobian against central differences (shared by the tests of
each objective term)."""

from __future__ import annotations

import numpy as np


def assert_objective_jacobian(fitter, x: np.ndarray, problem, sqrt_w: np.ndarray,
                              eps: float = 1e-6) -> None:
    res, jac = fitter.dense_system(x, problem, sqrt_w)
    assert np.isfinite(res).all() and np.isfinite(jac).all()
    numeric = np.empty_like(jac)
    for i in range(x.size):
        d = np.zeros(x.size)
        d[i] = eps
        hi, _ = fitter.dense_system(x + d, problem, sqrt_w)
        lo, _ = fitter.dense_system(x - d, problem, sqrt_w)
        numeric[:, i] = (hi - lo) / (2 * eps)
    np.testing.assert_allclose(jac, numeric, atol=2e-5 * max(1.0, np.abs(jac).max()))
