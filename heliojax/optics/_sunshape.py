"""Sun shapes: angular distributions of the incoming sunlight.

A sun shape is the distribution of the angle between a ray's direction and the
direction of the sun's centre. Every shape here is radially symmetric; a ray is
described by its 2-D angular offset ``(a, b)`` (rad) in the tangent plane of the
central sun direction, i.e. the unit vector to the sun of the ray is

    cos(r) s + sin(r)/r (a e1 + b e2),     r = |(a, b)|,

with ``s`` the central direction and ``(e1, e2)`` an orthonormal tangent basis
(:func:`tangent_basis`). Offsets are drawn with an explicit ``jax.random`` key:
a caller who wants fresh noise per optimisation step folds the step into the
key (``jax.random.fold_in(key, step)``); the same key reproduces the same rays.

Shapes:

* :class:`GaussianSun` — isotropic 2-D Gaussian, ``sigma`` per tangent axis
  (so the radial RMS is ``sqrt(2) sigma``).
* :class:`PillboxSun` — uniform disk of angular radius ``half_angle``
  (default 4.65 mrad, the sun's apparent radius).
* :class:`BuieSun` — Buie et al. (2003) circumsolar profile with parameter
  ``csr``: ``phi(t) = cos(0.326 t) / cos(0.308 t)`` on the disk (``t`` in mrad,
  ``t <= 4.65``) and ``exp(kappa) t**gamma`` in the aureole up to 43.6 mrad, with
  ``kappa = 0.9 ln(13.5 csr) csr**-0.3``, ``gamma = 2.2 ln(0.52 csr) csr**0.43 - 0.1``.
  Sampled by inverse CDF of the radial density ``phi(t) t`` on a table.
  ``realized_csr`` gives the circumsolar energy fraction the formula actually
  yields (it differs somewhat from the nominal parameter, a known property of
  Buie's fit).
* :class:`EffectiveSun` — a base shape convolved with a Gaussian mirror slope
  error (``2 * slope_error`` per axis: reflection doubles a normal's deviation),
  the usual "effective sun shape" approximation.
"""

from __future__ import annotations

import abc
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._limits import count_problem, real_problem

SUN_HALF_ANGLE = 4.65e-3
"""Apparent angular radius of the solar disk, rad."""


class AbstractSunShape(eqx.Module):
    """A radially symmetric angular distribution of sunlight.

    Subclasses map ``n_uniforms`` independent uniforms in ``(0, 1)`` to an angular
    offset (:meth:`from_uniforms`, an inverse-CDF transform), so the tracer can
    feed them from any random source keyed by ``jax.random`` (see
    :func:`uniforms`).
    """

    n_uniforms: typing.ClassVar[int] = 2

    @abc.abstractmethod
    def from_uniforms(self, u: Float[Array, "... k"]) -> Float[Array, "... 2"]:
        """Angular offsets ``(a, b)`` in rad from ``k = n_uniforms`` uniforms in ``(0, 1)``."""

    def sample(self, key: PRNGKeyArray, shape: tuple[int, ...], dtype=jnp.float32) -> Float[Array, "*shape 2"]:
        """Angular offsets ``(a, b)`` in rad of ``shape`` rays, drawn with ``key``."""
        return self.from_uniforms(uniforms(key, tuple(shape) + (self.n_uniforms,), dtype))

    def second_moment(self) -> float:
        """``E[a^2] = E[b^2]``, the per-axis mean square offset in rad^2 (for tests
        and analytic spot sizes)."""
        raise NotImplementedError


def _lowbias32(x):
    # Integer hash with good avalanche (C. Wellons' "lowbias32").
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def uniforms(
    key: PRNGKeyArray, shape: tuple[int, ...], dtype=jnp.float32, method: str = "hash"
) -> Float[Array, "*shape"]:
    """Uniform numbers in the open interval ``(0, 1)`` with 24-bit resolution.

    Args:
        key: a ``jax.random`` key; the same key gives the same numbers.
        shape: output shape.
        dtype: float dtype.
        method: ``"hash"`` (default): two 32-bit words drawn from ``key`` seed a
            counter-based integer hash (two rounds of ``lowbias32`` per number),
            ~5x faster on CPU than ``"jax"``, which calls ``jax.random.bits``
            (threefry or the key's implementation) for every number.
    """
    if any(isinstance(d, bool) or not isinstance(d, int | np.integer) or d < 0 for d in shape):
        # a negative size had failed in JAX's iota, naming neither the function nor the shape
        raise ValueError(f"uniforms: shape must be whole numbers >= 0, got {shape!r}"[:200])
    n = int(np.prod(shape))
    if method == "jax":
        bits = jax.random.bits(key, shape, jnp.uint32)
    elif method == "hash":
        seed = jax.random.bits(key, (2,), jnp.uint32)
        counter = jax.lax.iota(jnp.uint32, n).reshape(shape)
        bits = _lowbias32(_lowbias32(counter ^ seed[0]) + seed[1])
    else:
        raise ValueError(f"unknown method {method!r}")
    return ((bits >> 8).astype(dtype) + 0.5) * (1.0 / 16777216.0)


def _turn_polynomials() -> tuple[np.ndarray, np.ndarray]:
    """Least-squares polynomials (Chebyshev nodes) with ``sin(2 pi x) = x P(x^2)``
    and ``cos(2 pi x) = Q(x^2)`` on ``[-1/2, 1/2]``; max error ~1e-9."""
    x = 0.5 * np.cos(np.linspace(0.0, np.pi, 4001))
    y = x * x
    ps = np.linalg.lstsq(np.vander(y, 7, increasing=True) * x[:, None], np.sin(2 * np.pi * x), rcond=None)[0]
    pc = np.linalg.lstsq(np.vander(y, 8, increasing=True), np.cos(2 * np.pi * x), rcond=None)[0]
    return ps, pc


_SIN_P, _COS_P = _turn_polynomials()


def _horner(coef, y):
    out = jnp.full_like(y, float(coef[-1]))
    for c in coef[-2::-1]:
        out = out * y + float(c)
    return out


def _disk(radius: Float[Array, "..."], u: Float[Array, "..."]) -> Float[Array, "... 2"]:
    """``radius * (cos, sin)`` of the uniform angle ``2 pi (u - 1/2)`` by polynomials
    (no range reduction needed: ~3x faster than ``jnp.sin``/``jnp.cos`` on CPU)."""
    x = u - 0.5
    y = x * x
    return jnp.stack([radius * _horner(_COS_P, y), radius * (x * _horner(_SIN_P, y))], axis=-1)


MAX_SPREAD_RAD = 0.1
"""Largest angular width (rad) of :class:`GaussianSun`, :class:`PillboxSun` and
:class:`EffectiveSun`'s slope error, as ``heliojax trace`` takes them (100 mrad):
5.7 degrees per axis is no sun or mirror any more (a width in mrad or degrees, given
as radians, had traced a flux image of nothing)."""


def _check_width(cls: str, name: str, value: ArrayLike) -> None:
    """ValueError naming ``cls(name)`` unless the (concrete) width is finite and in
    ``[0, MAX_SPREAD_RAD]`` rad; a traced one is not checked."""
    if isinstance(value, jax.core.Tracer):  # pyright: ignore[reportAttributeAccessIssue]
        return
    v = np.asarray(value, float)
    if v.ndim:  # an array of widths had been taken for one sun (the ray tracer used the first)
        raise ValueError(f"{cls}: {name} must be one number (rad), got an array of shape {v.shape}")
    if not np.all(np.isfinite(v) & (v >= 0.0) & (v <= MAX_SPREAD_RAD)):
        hint = "; mrad? give it in rad (x 1e-3)" if np.all(np.isfinite(v) & (v > MAX_SPREAD_RAD)) else ""
        raise ValueError(f"{cls}: {name} must be finite and in [0, {MAX_SPREAD_RAD:g}] rad, got {value!r}{hint}")


def _gaussian_offsets(sigma: Float[Array, ""], u: Float[Array, "... 2"]) -> Float[Array, "... 2"]:
    """Isotropic Gaussian offsets of standard deviation ``sigma`` (rad) per axis from
    two uniforms (Box-Muller)."""
    r = jnp.asarray(sigma, u.dtype) * jnp.sqrt(-2.0 * jnp.log(u[..., 0]))
    return _disk(r, u[..., 1])


@typing.final
class GaussianSun(AbstractSunShape):
    """Isotropic Gaussian sun. ``sigma``: standard deviation per tangent axis, rad
    (finite, at most :data:`MAX_SPREAD_RAD`; ValueError otherwise)."""

    sigma: Float[Array, ""]

    def __init__(self, sigma: float | ArrayLike = 2.51e-3):
        _check_width("GaussianSun", "sigma", sigma)
        self.sigma = jnp.asarray(sigma)

    def from_uniforms(self, u):
        return _gaussian_offsets(self.sigma, u)

    def second_moment(self):
        return float(self.sigma) ** 2


@typing.final
class PillboxSun(AbstractSunShape):
    """Uniform disk of angular radius ``half_angle`` (rad; finite, at most
    :data:`MAX_SPREAD_RAD`, ValueError otherwise)."""

    half_angle: Float[Array, ""]

    def __init__(self, half_angle: float | ArrayLike = SUN_HALF_ANGLE):
        _check_width("PillboxSun", "half_angle", half_angle)
        self.half_angle = jnp.asarray(half_angle)

    def from_uniforms(self, u):
        return _disk(jnp.asarray(self.half_angle, u.dtype) * jnp.sqrt(u[..., 0]), u[..., 1])

    def second_moment(self):
        return float(self.half_angle) ** 2 / 4.0


_BUIE_DISK_MRAD = 4.65
_BUIE_OUTER_MRAD = 43.6


def buie_profile(theta_mrad: np.ndarray, csr: float) -> np.ndarray:
    """Buie's relative radiance ``phi(theta)`` (``theta`` in mrad, numpy), 0 beyond 43.6 mrad."""
    _check_csr("buie_profile", csr)
    t = np.asarray(theta_mrad, dtype=np.float64)
    kappa = 0.9 * np.log(13.5 * csr) * csr**-0.3
    gamma = 2.2 * np.log(0.52 * csr) * csr**0.43 - 0.1
    disk = np.cos(0.326 * t) / np.cos(0.308 * t)
    aureole = np.exp(kappa) * np.maximum(t, 1e-12) ** gamma
    out = np.where(t <= _BUIE_DISK_MRAD, disk, aureole)
    return np.where(t <= _BUIE_OUTER_MRAD, out, 0.0)


MAX_BUIE_TABLE = 10_000_000
"""Most intervals of :class:`BuieSun`'s inverse-CDF table (80 MB in float64)."""


def _check_csr(function: str, csr: typing.Any) -> None:
    """ValueError naming ``function`` unless ``csr`` is a real number in (0, 1) (0 had
    divided by zero, an array or a string failed in a comparison without its name)."""
    if real_problem(csr) is not None or not 0.0 < float(csr) < 1.0:
        raise ValueError(f"{function}: csr must be a circumsolar ratio in (0, 1), got {csr!r}"[:200])


@typing.final
class BuieSun(AbstractSunShape):
    """Buie circumsolar sun shape sampled by inverse CDF.

    The radial CDF of ``phi(t) t`` is integrated on a dense table (separately on
    each side of the disk edge, where the profile jumps) and inverted onto a
    uniform grid in probability, so sampling is one linear interpolation
    without a search.

    Attributes:
        csr: Buie's circumsolar-ratio parameter (0 < csr < 1).
        inverse_cdf: ``(n + 1,)`` angular radius in rad at probabilities ``0, 1/n, ..., 1``.

    Raises:
        ValueError: ``csr`` no real number in (0, 1), or ``n`` no whole number in
            ``[1, MAX_BUIE_TABLE]``.
    """

    csr: float = eqx.field(static=True)
    inverse_cdf: Float[Array, " n"]

    def __init__(self, csr: float = 0.05, n: int = 8192):
        _check_csr("BuieSun", csr)
        problem = count_problem(n, MAX_BUIE_TABLE)
        if problem is not None:  # 0 or less had built a table of one or no entry, sampled as garbage
            raise ValueError(f"BuieSun: n {problem}")
        self.csr = float(csr)
        t, cdf = _buie_cdf(self.csr)
        q = np.linspace(0.0, 1.0, n + 1)
        self.inverse_cdf = jnp.asarray(np.interp(q, cdf, t) * 1e-3)

    @property
    def realized_csr(self) -> float:
        """Fraction of the energy beyond the disk edge (4.65 mrad) of the tabulated profile."""
        t, cdf = _buie_cdf(self.csr)
        return float(1.0 - np.interp(_BUIE_DISK_MRAD, t, cdf))

    def from_uniforms(self, u):
        table = self.inverse_cdf.astype(u.dtype)
        n = table.shape[0] - 1
        x = u[..., 0] * n
        i = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, n - 1)
        f = x - i.astype(x.dtype)
        r = table[i] * (1.0 - f) + table[i + 1] * f
        return _disk(r, u[..., 1])

    def second_moment(self):
        t, cdf = _buie_cdf(self.csr)
        mid = 0.5 * (t[1:] + t[:-1]) * 1e-3
        return float(np.sum(np.diff(cdf) * mid**2) / 2.0)


def _buie_cdf(csr: float, n: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (mrad) and the normalised radial CDF of ``phi(t) t``."""
    disk = np.linspace(0.0, _BUIE_DISK_MRAD, n)
    aureole = np.geomspace(_BUIE_DISK_MRAD, _BUIE_OUTER_MRAD, n)

    def integrate(t, left_value=None):
        d = buie_profile(t, csr) * t
        if left_value is not None:
            d[0] = left_value
        return np.concatenate([[0.0], np.cumsum(0.5 * (d[1:] + d[:-1]) * np.diff(t))])

    c_disk = integrate(disk)
    edge = np.exp(0.9 * np.log(13.5 * csr) * csr**-0.3) * _BUIE_DISK_MRAD ** (
        2.2 * np.log(0.52 * csr) * csr**0.43 - 0.1
    )
    c_aur = integrate(aureole, left_value=edge * _BUIE_DISK_MRAD)
    t = np.concatenate([disk, aureole[1:]])
    cdf = np.concatenate([c_disk, c_disk[-1] + c_aur[1:]])
    return t, cdf / cdf[-1]


@typing.final
class EffectiveSun(AbstractSunShape):
    """``base`` convolved with Gaussian mirror slope errors.

    A slope error ``delta`` of the normal deflects the reflected ray by ``~2 delta``,
    so the offsets get an extra isotropic Gaussian of ``2 * slope_error`` per axis.

    Attributes:
        base: the sun shape.
        slope_error: RMS slope error per axis of the mirror normal, rad (finite, at most
            :data:`MAX_SPREAD_RAD`; ValueError otherwise).
    """

    base: AbstractSunShape
    slope_error: Float[Array, ""]

    def __init__(self, base: AbstractSunShape, slope_error: float | ArrayLike):
        _check_width("EffectiveSun", "slope_error", slope_error)
        self.base = base
        self.slope_error = jnp.asarray(slope_error)

    @property
    def n_uniforms(self) -> int:  # type: ignore[override]
        return self.base.n_uniforms + 2

    def from_uniforms(self, u):
        k = self.base.n_uniforms
        extra = _gaussian_offsets(2.0 * jnp.asarray(self.slope_error, u.dtype), u[..., k : k + 2])
        return self.base.from_uniforms(u[..., :k]) + extra

    def second_moment(self):
        return self.base.second_moment() + 4.0 * float(self.slope_error) ** 2


def tangent_basis(s: Float[Array, "... 3"]) -> tuple[Float[Array, "... 3"], Float[Array, "... 3"]]:
    """Orthonormal ``(e1, e2)`` perpendicular to unit ``s`` with ``e1 x e2 = s``.

    ``e1`` is horizontal (``up x s`` normalised) unless ``s`` is within 1.4 mrad of
    vertical, where east/north-based axes are used instead.
    """
    s = jnp.asarray(s)
    up = jnp.zeros_like(s).at[..., 2].set(1.0)
    north = jnp.zeros_like(s).at[..., 1].set(1.0)
    near_vertical = jnp.abs(s[..., 2:3]) > 1.0 - 1e-6
    ref = jnp.where(near_vertical, north, up)
    e1 = jnp.cross(ref, s)
    e1 = e1 / jnp.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = jnp.cross(s, e1)
    return e1, e2


def offsets_to_directions(offsets: Float[Array, "... 2"], sun: Float[Array, "3"]) -> Float[Array, "... 3"]:
    """Unit vectors to the sun of rays with angular ``offsets`` (rad) about ``sun``."""
    e1, e2 = tangent_basis(sun)
    a, b = offsets[..., 0:1], offsets[..., 1:2]
    r = jnp.sqrt(a * a + b * b)
    safe = jnp.where(r > 0, r, 1.0)
    sinc = jnp.where(r > 0, jnp.sin(r) / safe, 1.0)
    lead = (1,) * (offsets.ndim - 1)
    sun, e1, e2 = (v.reshape(lead + (3,)) for v in (sun, e1, e2))
    return jnp.cos(r) * sun + sinc * (a * e1 + b * e2)


__all__ = [
    "MAX_SPREAD_RAD",
    "SUN_HALF_ANGLE",
    "AbstractSunShape",
    "BuieSun",
    "EffectiveSun",
    "GaussianSun",
    "PillboxSun",
    "buie_profile",
    "offsets_to_directions",
    "tangent_basis",
    "uniforms",
]
