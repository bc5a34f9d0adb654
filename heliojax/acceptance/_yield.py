"""Level 2, step 4: field efficiency and yield over a typical year, contract
against measured values.

Optical chain of heliostat ``i`` at time ``t`` (all factors dimensionless)::

    eta_it = A_i / A_ref * rho_i * cos_it * eta_int,i * eta_att,i

* ``cos_it = sqrt((1 + s_t . u_i) / 2)``: cosine efficiency, ``s_t`` the unit
  vector to the sun, ``u_i`` the unit vector from the heliostat to the aim point
  (the aperture centre); the mirror normal is their bisector.
* ``eta_int,i``: intercept (1 - spillage) of a circular Gaussian beam on the
  receiver aperture, see :func:`intercept_efficiency`.
* ``eta_att,i = 0.99321 - 1.176e-4 d + 1.97e-8 d^2`` (``d`` slant range in m):
  the usual clear-day atmospheric attenuation fit (Leary & Hankins 1979, as
  used by DELSOL/HFLCAL), the same in both scenarios.
* ``A_i`` aperture (m^2), ``rho_i`` reflectance; ``A_ref`` the contract
  aperture, so a smaller measured aperture lowers the efficiency.

Beam model. The reflected beam of heliostat ``i`` is a circular Gaussian cone
about the ideal reflected ray with **per-axis** angular standard deviation::

    sigma_i^2 = sigma_sun^2 + 2 * slope_i^2 + tracking_i^2 / 2

where the inputs are the guideline's *radial* RMS values:

* ``tracking_i`` (mrad): radial RMS **beam** pointing error (angle between the
  actual and the ideal reflected ray), as heliojax's calibration reports it
  (``test_rms_mrad``). It already is a reflected-ray angle, so no factor 2; a
  radial RMS of an isotropic 2-D Gaussian is ``sqrt(2)`` times its per-axis std,
  hence ``/ 2`` in the variance. (A *normal* tracking error would enter as
  ``2 * tracking^2``.)
* ``slope_i`` (mrad): radial RMS slope deviation of the mirror **normal**
  (SolarPACES ``SD``). Reflection doubles a normal deviation (factor 4 in the
  variance), per axis ``SD^2 / 2``: ``4 * SD^2 / 2 = 2 SD^2``. The
  incidence-angle dependence of the out-of-plane component (astigmatism) is
  neglected.
* ``sigma_sun`` (mrad, per axis): Gaussian approximation of the sunshape,
  default 2.51 mrad (HFLCAL's value for a clear-sky sun).

With this model ``sigma_i`` does not depend on the time, so the intercept is
computed once per heliostat and only the cosine term follows the sun. Shading,
blocking and the curvature of the cylindrical receiver are not modelled (the
aperture is the plane rectangle of the ``receiver_outer_*`` corners).

Sun. The year is sampled at a fixed step (default 30 min, mid-interval times,
UTC) with :func:`heliojax._sun.solar_position` at the plant; each time is
weighted by a clear-sky DNI (Meinel model with the Kasten-Young air mass) and
times with the sun below ``min_elevation_deg`` are dropped. Monthly and annual
efficiencies are DNI-weighted means.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import os

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._errors import DataError
from .._geometry import TargetPlane, sun_direction, wgs84_to_enu
from .._limits import real_problem
from .._sun import solar_position
from ..paint import read_tower

SUN_SIGMA_MRAD = 2.51
"""Default per-axis standard deviation of the Gaussian sunshape (mrad)."""

JUELICH_COORDINATES = (50.913421122592574, 6.387824755874856, 87.0)
"""``power_plant_properties.coordinates`` of the Jülich tower (WGS84 deg, deg, m)."""

# ENU (m) of the receiver_outer_* corners of WRI1030197-tower-measurements.json
_JUELICH_RECEIVER_CORNERS = {
    "upper_left": (2.2577, 0.6841, 57.805),
    "upper_right": (-2.2952, 0.7361, 57.82),
    "lower_left": (2.2179, -1.7407, 52.596),
    "lower_right": (-2.2861, -1.715, 52.592),
}


def juelich_receiver() -> TargetPlane:
    """The Jülich receiver aperture (outer corners of the PAINT tower file's
    ``receiver`` entry, converted once to ENU) for use without the data files:
    4.53 m wide, 5.76 m high, centre about 55.2 m above the plant origin,
    facing north and tilted 25 deg down."""
    c = {k: jnp.asarray(v) for k, v in _JUELICH_RECEIVER_CORNERS.items()}
    return TargetPlane.from_corners(c["upper_left"], c["upper_right"], c["lower_left"], c["lower_right"])


def load_receiver(tower_file: str | os.PathLike) -> tuple[TargetPlane, tuple[float, float, float]]:
    """Receiver aperture and plant coordinates from a PAINT tower file.

    Args:
        tower_file: ``*-tower-measurements.json``.

    Returns:
        ``(aperture, (lat_deg, lon_deg, alt_m))``: the aperture rectangle in ENU
        (origin = the plant coordinates) from the ``receiver_outer_*`` corners,
        and the plant coordinates.

    Raises:
        DataError: missing or malformed fields.
    """
    tower = read_tower(tower_file)
    origin = tower.origin_lla
    receiver = tower.targets.get("receiver")
    if receiver is None:
        raise DataError(tower_file, "receiver", "missing")
    corners = {}
    for name in ("upper_left", "upper_right", "lower_left", "lower_right"):
        key = f"receiver_outer_{name}"
        if key not in receiver.points:
            raise DataError(tower_file, f"receiver.coordinates.{key}", "missing")
        corners[name] = wgs84_to_enu(jnp.asarray(receiver.points[key]), jnp.asarray(origin))
    try:
        plane = TargetPlane.from_corners(
            corners["upper_left"], corners["upper_right"], corners["lower_left"], corners["lower_right"]
        )
    except ValueError as e:  # corners of no rectangle: a NaN aperture had followed
        raise DataError(tower_file, "receiver.coordinates", str(e).removeprefix("TargetPlane.from_corners: ")) from None
    nv = receiver.normal
    if nv is not None:
        nv = np.asarray(nv, dtype=float)
        if float(np.dot(nv, np.asarray(plane.normal))) < 0.9 * np.linalg.norm(nv):
            raise DataError(tower_file, "receiver.normal_vector", "disagrees with the corner points")
    return plane, (origin[0], origin[1], origin[2])


def beam_sigma(
    tracking_mrad: Float[ArrayLike, "..."],
    slope_mrad: Float[ArrayLike, "..."],
    sun_sigma_mrad: float = SUN_SIGMA_MRAD,
) -> Float[Array, "..."]:
    """Per-axis angular std (rad) of the reflected beam (see the module docstring).

    Args:
        tracking_mrad: radial RMS beam pointing error (mrad).
        slope_mrad: radial RMS slope deviation of the mirror normal (mrad).
        sun_sigma_mrad: per-axis Gaussian sunshape std (mrad).

    Returns:
        ``sqrt(sun^2 + 2 slope^2 + tracking^2 / 2) * 1e-3`` in rad.

    Raises:
        ValueError: a (concrete, not traced) RMS or sunshape std that is negative or not
            finite (squared, a negative RMS had passed for a positive one).
    """
    for name, value in (
        ("tracking_mrad", tracking_mrad),
        ("slope_mrad", slope_mrad),
        ("sun_sigma_mrad", sun_sigma_mrad),
    ):
        if isinstance(value, jax.core.Tracer):  # pyright: ignore[reportAttributeAccessIssue]
            continue
        x = np.asarray(value, dtype=float)
        if not (np.isfinite(x) & (x >= 0.0)).all():
            raise ValueError(f"beam_sigma: {name} must be finite and >= 0 mrad (an RMS or std), got {value!r}"[:200])
    t = jnp.asarray(tracking_mrad)
    s = jnp.asarray(slope_mrad)
    return 1e-3 * jnp.sqrt(sun_sigma_mrad**2 + 2.0 * s**2 + 0.5 * t**2)


def atmospheric_attenuation(slant_m: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Clear-day transmittance over ``slant_m`` metres (valid below 1000 m)."""
    d = jnp.asarray(slant_m)
    return 0.99321 - 1.176e-4 * d + 1.97e-8 * d**2


def _aperture_corners(aperture: TargetPlane) -> Float[Array, "4 3"]:
    hw, hh = aperture.half_width, aperture.half_height
    signs = jnp.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    return (
        aperture.centre[None]
        + (signs[:, :1] * hw) * aperture.u_axis[None]
        + (signs[:, 1:] * hh) * aperture.v_axis[None]
    )


@jax.jit
def _intercept(positions, centre, corners, sigma, nodes, weights):
    w = centre[None] - positions  # (n, 3)
    u = w / jnp.linalg.norm(w, axis=-1, keepdims=True)
    up = jnp.zeros_like(u).at[:, 2].set(1.0)
    e1 = jnp.cross(up, u)
    e1 = e1 / jnp.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = jnp.cross(u, e1)
    v = corners[None, :, :] - positions[:, None, :]  # (n, 4, 3)
    along = jnp.sum(v * u[:, None, :], axis=-1)
    g = jnp.stack([jnp.sum(v * e1[:, None, :], -1), jnp.sum(v * e2[:, None, :], -1)], -1) / along[..., None]
    a = g  # edge start (n, 4, 2)
    b = jnp.roll(g, -1, axis=1)  # edge end
    ta = jnp.arctan2(a[..., 1], a[..., 0])
    dtheta = jnp.arctan2(b[..., 1], b[..., 0]) - ta
    dtheta = jnp.mod(dtheta + jnp.pi, 2 * jnp.pi) - jnp.pi
    ab = b - a
    h = jnp.abs(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]) / jnp.linalg.norm(ab, axis=-1)
    t = -jnp.sum(a * ab, -1) / jnp.sum(ab * ab, -1)
    foot = a + t[..., None] * ab
    t0 = jnp.arctan2(foot[..., 1], foot[..., 0])
    theta = ta[..., None] + dtheta[..., None] * 0.5 * (nodes[None, None] + 1.0)  # (n, 4, q)
    r = h[..., None] / jnp.cos(theta - t0[..., None])
    s2 = (sigma**2)[:, None, None]
    f = -jnp.expm1(-0.5 * r**2 / s2)
    integral = 0.5 * dtheta * jnp.sum(weights[None, None] * f, axis=-1)  # (n, 4)
    return jnp.abs(jnp.sum(integral, axis=-1)) / (2 * jnp.pi)


def intercept_efficiency(
    positions: Float[ArrayLike, "n 3"],
    aperture: TargetPlane,
    sigma_rad: Float[ArrayLike, " n"],
    *,
    n_nodes: int = 48,
) -> Float[Array, " n"]:
    """Fraction of a circular Gaussian beam that enters the aperture rectangle.

    Each heliostat aims at the aperture centre. Beam directions are
    ``u + xi_1 e_1 + xi_2 e_2`` with ``xi ~ N(0, sigma^2 I)`` in the plane
    tangent to the central ray ``u`` (gnomonic coordinates), so the beam is
    exactly Gaussian on any plane normal to ``u``. The aperture rectangle seen
    from the heliostat, projected centrally into these coordinates, is a
    quadrilateral (its obliquity and the perspective are kept exactly, no
    small-angle projection). The Gaussian mass of the quadrilateral is the sum,
    over its edges, of the mass of the triangle (origin, edge): in polar
    coordinates ``(1/2pi) int (1 - exp(-r(theta)^2 / 2 sigma^2)) dtheta`` with
    ``r(theta) = h / cos(theta - theta_0)`` the distance to the edge's line, a
    smooth 1-D integral evaluated by Gauss-Legendre quadrature (``n_nodes``
    per edge; closed-form radial part). Signed angles make the sum valid for
    any aim point. Vectorised over heliostats.

    Args:
        positions: ``(n, 3)`` ENU m of the heliostat (mirror centres).
        aperture: the receiver aperture (:class:`heliojax._geometry.TargetPlane`).
        sigma_rad: ``(n,)`` per-axis angular beam std in rad (:func:`beam_sigma`).
        n_nodes: Gauss-Legendre nodes per edge.

    Returns:
        ``(n,)`` intercept factors in [0, 1].
    """
    p = jnp.asarray(positions)
    sigma = jnp.broadcast_to(jnp.asarray(sigma_rad, dtype=p.dtype), p.shape[:1])
    x, wq = np.polynomial.legendre.leggauss(n_nodes)
    return _intercept(
        p,
        aperture.centre.astype(p.dtype),
        _aperture_corners(aperture).astype(p.dtype),
        sigma,
        jnp.asarray(x, p.dtype),
        jnp.asarray(wq, p.dtype),
    )


def cosine_efficiency(
    positions: Float[ArrayLike, "n 3"],
    aim: Float[ArrayLike, "3"],
    sun: Float[ArrayLike, "t 3"],
) -> Float[Array, "t n"]:
    """Cosine factor ``sqrt((1 + s . u) / 2)`` for every (time, heliostat).

    Args:
        positions: ``(n, 3)`` ENU m.
        aim: ``(3,)`` ENU m aim point.
        sun: ``(t, 3)`` unit vectors to the sun.
    """
    positions = jnp.asarray(positions)
    w = jnp.broadcast_to(jnp.asarray(aim), positions.shape) - positions
    u = w / jnp.linalg.norm(w, axis=-1, keepdims=True)
    return jnp.sqrt(jnp.clip(0.5 * (1.0 + jnp.asarray(sun) @ u.T), 0.0, 1.0))


def clear_sky_dni(elevation_rad: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Clear-sky direct normal irradiance (W/m^2), Meinel model
    ``1353 * 0.7 ** (AM ** 0.678)`` with the Kasten-Young (1989) air mass; 0 below
    the horizon."""
    el = jnp.asarray(elevation_rad)
    el_deg = jnp.rad2deg(el)
    safe = jnp.maximum(el_deg, 0.0)
    am = 1.0 / (jnp.sin(jnp.deg2rad(safe)) + 0.50572 * (safe + 6.07995) ** -1.6364)
    return jnp.where(el > 0, 1353.0 * 0.7 ** (am**0.678), 0.0)


@dataclasses.dataclass(frozen=True)
class SunSeries:
    """Sun over a year at the plant.

    Attributes:
        unix_time_s: ``(t,)`` UTC times (s), mid-interval.
        month: ``(t,)`` month 1..12 (UTC).
        direction: ``(t, 3)`` unit ENU vectors to the sun.
        dni: ``(t,)`` clear-sky DNI weight (W/m^2).
        step_s: sampling step (s).
    """

    unix_time_s: Float[np.ndarray, " t"]
    month: Int[np.ndarray, " t"]
    direction: Float[np.ndarray, "t 3"]
    dni: Float[np.ndarray, " t"]
    step_s: float


def typical_year(
    latitude_deg: float,
    longitude_deg: float,
    altitude_m: float = 0.0,
    *,
    year: int = 2023,
    step_minutes: float = 30.0,
    min_elevation_deg: float = 5.0,
) -> SunSeries:
    """Sun positions (NREL SPA, :func:`heliojax._sun.solar_position`) over one year.

    Args:
        latitude_deg, longitude_deg, altitude_m: plant location (WGS84).
        year: calendar year sampled (UTC).
        step_minutes: sampling step, in [1, 1440] (a contract's range).
        min_elevation_deg: drop times with the sun lower than this.

    Raises:
        ValueError: a value that is not a finite number (a NaN latitude gave a year
            without sun), a ``step_minutes`` outside [1, 1440] (0 divided by zero, a
            negative step gave a year without sun); a latitude beyond a pole.
    """
    for name, value in (
        ("latitude_deg", latitude_deg),
        ("longitude_deg", longitude_deg),
        ("altitude_m", altitude_m),
        ("min_elevation_deg", min_elevation_deg),
        ("step_minutes", step_minutes),
    ):
        problem = real_problem(value)
        if problem is not None:
            raise ValueError(f"typical_year: {name} {problem}")
    if not 1.0 <= step_minutes <= 1440.0:
        raise ValueError(f"typical_year: step_minutes must lie in [1, 1440] minutes, got {step_minutes!r}")
    start = _dt.datetime(year, 1, 1, tzinfo=_dt.UTC).timestamp()
    end = _dt.datetime(year + 1, 1, 1, tzinfo=_dt.UTC).timestamp()
    step = 60.0 * step_minutes
    t = np.arange(start + 0.5 * step, end, step)
    pos = solar_position(jnp.asarray(t), latitude_deg, longitude_deg, altitude_m)
    az, el = np.asarray(pos.azimuth), np.asarray(pos.elevation)
    keep = el > np.deg2rad(min_elevation_deg)
    t, az, el = t[keep], az[keep], el[keep]
    month = (t.astype("datetime64[s]").astype("datetime64[M]").astype(int) % 12) + 1
    direction = np.asarray(sun_direction(jnp.asarray(az), jnp.asarray(el)))
    return SunSeries(t, month.astype(int), direction, np.asarray(clear_sky_dni(jnp.asarray(el))), step)


@dataclasses.dataclass(frozen=True)
class YieldResult:
    """Field efficiency of one scenario.

    Attributes:
        annual: DNI-weighted annual field efficiency.
        monthly: ``(12,)`` DNI-weighted monthly efficiencies (NaN for a month
            without sun samples).
        intercept: ``(n,)`` intercept factor per heliostat.
        annual_per_heliostat: ``(n,)`` DNI-weighted annual efficiency per heliostat.
        dni_kwh_m2: ``(12,)`` clear-sky direct normal irradiation per month (kWh/m^2).
    """

    annual: float
    monthly: Float[np.ndarray, " 12"]
    intercept: Float[np.ndarray, " n"]
    annual_per_heliostat: Float[np.ndarray, " n"]
    dni_kwh_m2: Float[np.ndarray, " 12"]


def field_efficiency(
    positions: Float[ArrayLike, "n 3"],
    aperture: TargetPlane,
    sun: SunSeries,
    *,
    tracking_mrad: Float[ArrayLike, " n"],
    slope_mrad: Float[ArrayLike, " n"] | float = 0.0,
    reflectance: Float[ArrayLike, " n"] | float = 1.0,
    aperture_m2: Float[ArrayLike, " n"] | float = 1.0,
    reference_aperture_m2: float | None = None,
    sun_sigma_mrad: float = SUN_SIGMA_MRAD,
) -> YieldResult:
    """Monthly and annual field efficiency of a heliostat field (see the module docstring).

    Args:
        positions: ``(n, 3)`` ENU m of the heliostats.
        aperture: receiver aperture.
        sun: the year's sun samples (:func:`typical_year`).
        tracking_mrad: ``(n,)`` radial RMS beam pointing errors.
        slope_mrad: ``(n,)`` radial RMS slope deviations (scalar broadcasts).
        reflectance: ``(n,)`` reflectances.
        aperture_m2: ``(n,)`` net apertures.
        reference_aperture_m2: ``A_ref``; default the mean of ``aperture_m2``.
        sun_sigma_mrad: per-axis sunshape std.

    Returns:
        A :class:`YieldResult`.
    """
    p = jnp.asarray(positions)
    n = p.shape[0]
    bc = lambda x: jnp.broadcast_to(jnp.asarray(x, dtype=p.dtype), (n,))  # noqa: E731
    area = bc(aperture_m2)
    a_ref = float(jnp.mean(area)) if reference_aperture_m2 is None else float(reference_aperture_m2)
    sigma = beam_sigma(bc(tracking_mrad), bc(slope_mrad), sun_sigma_mrad)
    eta_int = intercept_efficiency(p, aperture, sigma)
    slant = jnp.linalg.norm(aperture.centre[None] - p, axis=-1)
    static = area / a_ref * bc(reflectance) * eta_int * atmospheric_attenuation(slant)  # (n,)
    monthly = np.full(12, np.nan)
    dni_month = np.zeros(12)
    per_h = jnp.zeros(n, dtype=p.dtype)
    total_w = 0.0
    for m in range(1, 13):  # loop over months; each is a (t_m, n) matrix product
        sel = sun.month == m
        if not sel.any():
            continue
        w = jnp.asarray(sun.dni[sel], dtype=p.dtype)
        cos_w = w @ cosine_efficiency(p, aperture.centre, jnp.asarray(sun.direction[sel], dtype=p.dtype))
        monthly[m - 1] = float(jnp.sum(cos_w * static) / (n * jnp.sum(w)))
        dni_month[m - 1] = float(jnp.sum(w)) * sun.step_s / 3.6e6
        per_h = per_h + cos_w * static
        total_w += float(jnp.sum(w))
    per_h = np.asarray(per_h) / total_w
    return YieldResult(
        annual=float(per_h.mean()),
        monthly=monthly,
        intercept=np.asarray(eta_int),
        annual_per_heliostat=per_h,
        dni_kwh_m2=dni_month,
    )
