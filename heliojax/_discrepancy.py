"""Model discrepancy: what a heliostat's kinematic model cannot express, as a
Gaussian process over the mirror normal.

A real heliostat deviates from any parametric model in ways that vary smoothly
with its pose (actuator non-linearity, structural deflection, a facet canting the
model lacks). For planning calibration measurements this matters: a design that
trusts the model exactly puts measurements where the model has the most leverage,
the extreme poses, where a real heliostat deviates most from it, and learns little
about the poses it operates in. heliojax models the discrepancy of each residual
component ``d_i(n)`` at mirror normal ``n`` (unit ENU vector) as a zero-mean
Gaussian process, independent between the two components and between heliostats,
with the squared-exponential kernel::

    k(n, n') = tau^2 exp(-|n - n'|^2 / (2 l^2))

(``tau``: :attr:`ModelDiscrepancy.amplitude_mrad`, ``l``: :attr:`ModelDiscrepancy.length`,
a chord length on the unit sphere, about the angle in rad for small angles).

:func:`estimate_discrepancy` learns ``tau`` and ``l`` from a fleet's own fit
residuals by the empirical variogram (Cressie 1993, ch. 2): for pairs of records
of one heliostat ``gamma(h) = 0.5 E[(r_i - r_j)^2] = s^2 + tau^2 (1 - exp(-h^2 / 2 l^2))``
at normal distance ``h``, with the robust Cressie-Hawkins estimate per distance
bin and Cressie's weighted least squares fit (``s``: the uncorrelated nugget,
measurement noise). Two biases are stated, not corrected: a fit absorbs the part
of the discrepancy its parameters can express (``tau`` is what remains), and slow
drift between records taken in different seasons also shows up as correlation
over normal distance.

For planning (:func:`heliojax.plan_calibration`) the process is represented by its
values at ``B`` inducing normals (the projected-process approximation), whitened:
``d(n) = k(n, U) L^-T v`` with ``K_UU = L L^T`` and ``v ~ N(0, I)``
(:func:`discrepancy_features`); the ``2 B`` coefficients ``v`` join the free
parameters, so that the design criterion counts what a measurement teaches about
the discrepancy where the heliostat operates, and how the discrepancy at the
measured pose dilutes what it teaches about the parameters.
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._geometry import bisector_normal, normalize

DISCREPANCY_INDUCING = 32
"""Inducing normals per heliostat of the planner's discrepancy basis."""

_JITTER = 1e-8
"""Relative diagonal jitter of ``K_UU`` (numerical only)."""


def _as_float(x: typing.Any) -> np.ndarray:
    return np.asarray(x, np.float64)


@typing.final
class ModelDiscrepancy(eqx.Module):
    """Squared-exponential Gaussian process of the model discrepancy over the mirror
    normal (module docstring).

    Attributes:
        amplitude_mrad: ``tau``, standard deviation of each residual component's
            discrepancy, mrad (0: the model is taken as exact).
        length: ``l``, correlation length as a chord on the unit sphere of mirror
            normals (about rad for small angles).
        nugget_mrad: the uncorrelated part of the residuals found beside it (noise), mrad.
    """

    amplitude_mrad: Float[np.ndarray, ""] = eqx.field(converter=_as_float)
    length: Float[np.ndarray, ""] = eqx.field(converter=_as_float)
    nugget_mrad: Float[np.ndarray, ""] = eqx.field(converter=_as_float, default=0.0)

    def __check_init__(self):
        if not (np.isfinite(self.amplitude_mrad) and self.amplitude_mrad >= 0.0):
            raise ValueError(f"ModelDiscrepancy: amplitude_mrad must be finite and >= 0, got {self.amplitude_mrad}")
        if not (np.isfinite(self.length) and self.length > 0.0):
            raise ValueError(f"ModelDiscrepancy: length must be finite and > 0, got {self.length}")
        if not (np.isfinite(self.nugget_mrad) and self.nugget_mrad >= 0.0):
            raise ValueError(f"ModelDiscrepancy: nugget_mrad must be finite and >= 0, got {self.nugget_mrad}")

    def kernel(self, a: Float[ArrayLike, "*n 3"], b: Float[ArrayLike, "*m 3"]) -> Float[Array, "*n *m"]:
        """``k(a, b)`` (mrad^2) between every normal of ``a`` and every normal of ``b``."""
        a = jnp.asarray(a)
        b = jnp.asarray(b, a.dtype)
        dot = jnp.tensordot(a, b, axes=([-1], [-1]))
        return jnp.asarray(self.amplitude_mrad) ** 2 * jnp.exp(-(2.0 - 2.0 * dot) / (2.0 * self.length**2))

    def variogram(self, distance: Float[ArrayLike, "*n"]) -> Float[Array, "*n"]:
        """``gamma(h) = s^2 + tau^2 (1 - exp(-h^2 / 2 l^2))`` (mrad^2) at chord distance ``h``."""
        h = jnp.asarray(distance)
        tau2 = jnp.asarray(self.amplitude_mrad) ** 2
        return jnp.asarray(self.nugget_mrad) ** 2 + tau2 * (1.0 - jnp.exp(-(h**2) / (2.0 * self.length**2)))


def mirror_normals(
    position: Float[ArrayLike, "*h 3"], sun: Float[ArrayLike, "*h k 3"], aim: Float[ArrayLike, "*h k 3"]
) -> Float[Array, "*h k 3"]:
    """Mirror normal (unit ENU) that reflects ``sun`` (unit vector to the sun) from
    ``position`` (ENU m) to ``aim`` (ENU m): the bisector of the two directions."""
    p = jnp.asarray(position)[..., None, :]
    return bisector_normal(jnp.asarray(sun), normalize(jnp.asarray(aim) - p))


def _cressie_hawkins(diff: np.ndarray) -> float:
    """Robust semivariance of differences ``diff`` (Cressie & Hawkins 1980)."""
    n = diff.size
    return float(np.mean(np.sqrt(np.abs(diff))) ** 4 / (0.457 + 0.494 / n) / 2.0)


def estimate_discrepancy(
    residuals: Float[ArrayLike, "H M 2"],
    normals: Float[ArrayLike, "H M 3"],
    use: Bool[ArrayLike, "H M"],
    *,
    bins: int = 12,
    lengths: Float[ArrayLike, " L"] | None = None,
) -> ModelDiscrepancy:
    """Learn the discrepancy process from a fleet's fit residuals (module docstring).

    Args:
        residuals: ``(H, M, 2)`` residual components of fitted records, mrad.
        normals: ``(H, M, 3)`` mirror normal of each record (:func:`mirror_normals`).
        use: ``(H, M)`` records to learn from (inliers of fitted heliostats).
        bins: distance bins of equal pair counts.
        lengths: candidate correlation lengths (chord); default 24 from 0.01 to 1.5
            on a log scale. Lengths below the mean distance of the closest bin's
            pairs are not tried: a process that short cannot be told from noise.

    Returns:
        The :class:`ModelDiscrepancy` of the weighted least-squares variogram fit
        (``amplitude_mrad = 0`` when no pose-correlated structure is found, or
        when fewer than ``3 * bins`` pairs are available).
    """
    from scipy.optimize import nnls

    r = np.asarray(residuals, float)
    n = np.asarray(normals, float)
    use = np.asarray(np.asarray(use, bool) & np.all(np.isfinite(r), axis=-1) & np.all(np.isfinite(n), axis=-1), bool)
    dist, diff = [], []
    for k in np.flatnonzero(use.any(axis=1)):  # pairs within a heliostat; not a hot path
        idx = np.flatnonzero(use[k])
        i, j = np.triu_indices(idx.size, 1)
        dist.append(np.linalg.norm(n[k, idx[i]] - n[k, idx[j]], axis=-1))
        diff.append(r[k, idx[i]] - r[k, idx[j]])
    h = np.concatenate(dist) if dist else np.zeros(0)
    d = np.concatenate(diff) if diff else np.zeros((0, 2))
    if h.size < 3 * bins:
        nugget = float(np.sqrt(0.5 * np.median(d**2))) if d.size else 0.0
        return ModelDiscrepancy(amplitude_mrad=0.0, length=1.0, nugget_mrad=nugget)
    edges = np.quantile(h, np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, h, side="right") - 1, 0, bins - 1)
    centre, gamma, count = [], [], []
    for b in range(bins):
        sel = which == b
        if sel.sum() < 3:
            continue
        centre.append(float(np.mean(h[sel])))
        gamma.append(0.5 * (_cressie_hawkins(d[sel, 0]) + _cressie_hawkins(d[sel, 1])))
        count.append(int(sel.sum()))
    hc, g, nc = np.asarray(centre), np.asarray(gamma), np.asarray(count, float)
    grid = np.geomspace(0.01, 1.5, 24) if lengths is None else np.asarray(lengths, float)
    # a correlation length below the closest pairs' distance cannot be told from noise
    grid = grid[grid >= hc[0]] if np.any(grid >= hc[0]) else grid[-1:]
    best = (np.inf, 0.0, 1.0, float(np.sqrt(np.min(g))))
    for ell in grid:
        shape = 1.0 - np.exp(-(hc**2) / (2.0 * ell**2))
        a = np.stack([np.ones_like(hc), shape], axis=1)
        # Cressie's weights N_b / gamma_b^2 (iterated once on the fitted variogram)
        w = np.sqrt(nc) / np.maximum(g, 1e-300)
        coef, _ = nnls(a * w[:, None], g * w)
        fitted = a @ coef
        w = np.sqrt(nc) / np.maximum(fitted, 1e-300)
        coef, _ = nnls(a * w[:, None], g * w)
        sse = float(np.sum((w * (a @ coef - g)) ** 2))
        if sse < best[0]:
            best = (sse, float(coef[1]), float(ell), float(np.sqrt(coef[0])))
    _, tau2, ell, nugget = best
    return ModelDiscrepancy(amplitude_mrad=float(np.sqrt(max(tau2, 0.0))), length=ell, nugget_mrad=nugget)


@jax.jit
def _farthest_points(points: Float[Array, "H N 3"], valid: Bool[Array, "H N"], count_like: Float[Array, " B"]):
    def one(p, ok):
        start = jnp.argmax(ok)
        far = jnp.where(ok, jnp.linalg.norm(p - p[start][None], axis=-1), -jnp.inf)

        def step(carry, _):
            far = carry
            k = jnp.argmax(far)
            far = jnp.minimum(far, jnp.where(ok, jnp.linalg.norm(p - p[k][None], axis=-1), -jnp.inf))
            return far, p[k]

        _, rest = jax.lax.scan(step, far, None, length=count_like.shape[0] - 1)
        return jnp.concatenate([p[start][None], rest], axis=0)

    return jax.vmap(one)(points, valid)


def inducing_normals(
    normals: Float[ArrayLike, "H N 3"], valid: Bool[ArrayLike, "H N"], count: int = DISCREPANCY_INDUCING
) -> Float[Array, "H B 3"]:
    """``count`` inducing normals per heliostat spread over its ``valid`` normals by
    farthest-point sampling (the first valid normal, then repeatedly the one
    farthest from those taken). With fewer distinct normals than ``count``, normals
    repeat (harmless: the whitened basis ignores duplicates up to the jitter)."""
    p = jnp.asarray(normals)
    return _farthest_points(p, jnp.asarray(valid, bool), jnp.zeros(int(count), p.dtype))


def discrepancy_features(
    discrepancy: ModelDiscrepancy, normals: Float[ArrayLike, "*k 3"], inducing: Float[ArrayLike, "B 3"]
) -> Float[Array, "*k B"]:
    """Whitened projected-process features ``phi(n) = k(n, U) L^-T`` (mrad), so that
    ``d(n) = phi(n) v`` with ``v ~ N(0, I)`` (module docstring). Zero when the
    amplitude is 0."""
    u = jnp.asarray(inducing)
    k_uu = discrepancy.kernel(u, u)
    b = u.shape[0]
    jitter = (_JITTER * discrepancy.amplitude_mrad**2 + 1e-300) * jnp.eye(b, dtype=k_uu.dtype)
    chol = jnp.linalg.cholesky(k_uu + jitter)
    k_nu = discrepancy.kernel(jnp.asarray(normals, u.dtype), u)  # (*k, B)
    flat = k_nu.reshape(-1, b)
    phi = jax.scipy.linalg.solve_triangular(chol, flat.T, lower=True).T
    return phi.reshape(k_nu.shape)


def augment_jacobian(jac: Float[Array, "*k 2 F"], features: Float[Array, "*k B"]) -> Float[Array, "*k 2 F+2*B"]:
    """Append the discrepancy coefficients to a Jacobian of the two residual
    components: row ``i`` gains ``phi`` in the block of component ``i``."""
    phi = jnp.asarray(features, jac.dtype)[..., None, :]
    zero = jnp.zeros_like(phi)
    first = jnp.concatenate([phi, zero], axis=-1)
    second = jnp.concatenate([zero, phi], axis=-1)
    return jnp.concatenate([jac, jnp.concatenate([first, second], axis=-2)], axis=-1)


__all__ = [
    "DISCREPANCY_INDUCING",
    "ModelDiscrepancy",
    "augment_jacobian",
    "discrepancy_features",
    "estimate_discrepancy",
    "inducing_normals",
    "mirror_normals",
]
