"""A second route to the evidence of an effect linear in its parameters, for the tests
of discovery's criterion: the marginal likelihood of the residual rows themselves
(``n x n``), no information matrices."""

from __future__ import annotations

import numpy as np

from heliojax.discovery._screen import PRIOR_SCALES


def gaussian_evidence(x: np.ndarray, r: np.ndarray, sigma2: float, prior_var: np.ndarray) -> float:
    """``-2 log`` Bayes factor of ``r = x beta + e``, ``beta ~ N(0, diag(prior_var))``,
    ``e ~ N(0, sigma2 I)``, against ``r = e``: ``log det(C) - n log sigma2 + r^T C^-1 r
    - r^T r / sigma2`` with ``C = sigma2 I + x diag(prior_var) x^T``."""
    n = len(r)
    c = sigma2 * np.eye(n) + (x * prior_var) @ x.T
    return float(np.linalg.slogdet(c)[1] - n * np.log(sigma2) + r @ np.linalg.solve(c, r) - r @ r / sigma2)


def scale_and_penalty(blocks) -> tuple[float, float]:
    """The hyperprior's choice over :data:`PRIOR_SCALES` for independent ``blocks`` of
    ``(x, r, sigma2, typical)``: the scale of largest summed evidence (1 unless another is
    better) and ``-2 log`` of the evidence averaged over the scales relative to the
    evidence at that scale."""
    e = np.array([sum(gaussian_evidence(x, r, s2, (s * t) ** 2) for x, r, s2, t in blocks) for s in PRIOR_SCALES])
    one = PRIOR_SCALES.tolist().index(1.0)
    best = int(np.argmin(e)) if np.min(e) < e[one] - 1e-9 else one
    d = -0.5 * (e - e[best])
    return float(PRIOR_SCALES[best]), float(-2.0 * np.log(np.mean(np.exp(d))))
