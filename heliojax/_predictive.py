"""The predicted pointing-error distribution of a calibrated heliostat.

A record (or a command) ``dt`` days after the heliostat's last fitted record has a
2-D residual ``r`` (mrad, the beam's two tangent components) predicted as a
bivariate Student t centred on zero with scale matrix ``S + q dt I`` and
``tail_dof`` degrees of freedom: ``S = J C J^T + noise^2 I`` from the fit
(:func:`heliojax.residual_prediction`), ``q`` (mrad^2 per day per component) a
random-walk drift. ``tail_dof = inf`` is the Gaussian ``N(0, S + q dt I)``.

The t is the Gaussian scale mixture that real records need: maintenance episodes,
gross errors and effects the model lacks make the held-out errors of real
heliostats heavier-tailed than a Gaussian (README, "Predictive uncertainty"). With
``d^2 = r^T (S + q dt I)^-1 r``, ``P(d^2 <= x) = 1 - (1 + x / nu)^(-nu / 2)``
(``d^2 / 2`` follows an F(2, nu) law), which tends to the chi-square(2)
``1 - exp(-x / 2)`` as ``nu -> inf``.
"""

from __future__ import annotations

import math

import numpy as np
from jaxtyping import Float

_DRIFT_GRID = np.concatenate([[0.0], np.geomspace(1e-6, 1e3, 91)])  # mrad^2 / day
_DOF_GRID = np.concatenate([np.geomspace(0.5, 1e3, 67), [np.inf]])


def prediction_region_d2(probability: float, tail_dof: float = math.inf) -> float:
    """The squared Mahalanobis radius ``x`` with ``P(d^2 <= x) = probability`` of the
    predicted 2-D pointing error (see the module docstring): ``-2 ln(1 - p)`` for a
    Gaussian (``tail_dof = inf``; 5.991 at 95 %), ``nu ((1 - p)^(-2 / nu) - 1)``
    for a Student t with ``nu = tail_dof`` degrees of freedom.

    Raises:
        ValueError: ``probability`` outside (0, 1) or ``tail_dof`` not positive.
    """
    if not 0.0 < probability < 1.0:
        raise ValueError(f"probability must be in (0, 1); got {probability}")
    if not tail_dof > 0.0:
        raise ValueError(f"tail_dof must be positive (inf: Gaussian); got {tail_dof}")
    if math.isinf(tail_dof):
        return -2.0 * math.log1p(-probability)
    return tail_dof * math.expm1(-2.0 / tail_dof * math.log1p(-probability))


def region_radius(largest_scale_eigenvalue, probability: float, tail_dof: float = math.inf):
    """Radius (the scale's units' square root, mrad) of the circle that holds the
    predicted error with at least ``probability``: the region's semi-major axis
    ``sqrt(prediction_region_d2(probability, tail_dof) * largest eigenvalue)``. Works on
    NumPy and JAX arrays alike."""
    return (prediction_region_d2(probability, tail_dof) * largest_scale_eigenvalue) ** 0.5


def _log_likelihood(
    d2: Float[np.ndarray, "Q N"], logdet: Float[np.ndarray, "Q N"], dof: float
) -> Float[np.ndarray, " Q"]:
    """Summed log-likelihood (less ``N log 2 pi``) of bivariate t residuals with
    ``dof`` degrees of freedom (``inf``: Gaussian) for each drift (rows)."""
    kernel = -0.5 * d2 if math.isinf(dof) else -(dof / 2.0 + 1.0) * np.log1p(d2 / dof)
    return np.sum(kernel - 0.5 * logdet, axis=-1)


def fit_drift_and_tails(
    residual_mrad: Float[np.ndarray, "N 2"],
    scale_mrad2: Float[np.ndarray, "N 2 2"],
    days: Float[np.ndarray, " N"],
) -> tuple[float, float]:
    """Maximum-likelihood drift ``q`` (mrad^2/day per component) and ``tail_dof`` of
    the predicted distribution (module docstring) from validation residuals with
    their fitted scale ``S`` and days since the fit.

    The likelihood is maximised on a grid: ``q`` in 0 and 1e-6-1e3 (ratio 1.26),
    ``tail_dof`` in 0.5-1000 (ratio 1.12) and ``inf``; a Gaussian fit to Gaussian
    residuals is chosen over ``tail_dof = 1000`` whenever it is at least as likely.

    Returns:
        ``(q, tail_dof)``.
    """
    r = np.asarray(residual_mrad, float)
    s = np.asarray(scale_mrad2, float)
    t = np.asarray(days, float)
    total = s[None] + (_DRIFT_GRID[:, None] * t[None, :])[..., None, None] * np.eye(2)
    d2 = np.einsum("ni,qnij,nj->qn", r, np.linalg.inv(total), r)
    logdet = np.linalg.slogdet(total)[1]
    ll = np.stack([_log_likelihood(d2, logdet, float(v)) for v in _DOF_GRID], axis=1)  # (Q, V)
    # the last index of the maximum: among equally likely values, the Gaussian and the smallest drift
    iq, iv = np.unravel_index(np.argmax(ll[:, ::-1]), ll.shape)
    return float(_DRIFT_GRID[iq]), float(_DOF_GRID[::-1][iv])


__all__ = ["fit_drift_and_tails", "prediction_region_d2", "region_radius"]
