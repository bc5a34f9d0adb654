"""Geometry: geodesy, sun vectors, reflection and ray-plane intersection.

Coordinate convention of heliojax (the one place it is written down)
====================================================================

* **Frame.** Everything inside the library lives in a local east-north-up (ENU)
  Cartesian frame, in metres, whose origin is the plant reference point
  ``power_plant_properties.coordinates`` of the PAINT tower file. ``x`` = east,
  ``y`` = north, ``z`` = up (the ellipsoid normal at the origin). The frame is
  exact: WGS84 geodetic -> ECEF -> ENU with no flat-earth approximation.
* **Angles.** Radians inside the library. Degrees appear only at the data
  boundary (PAINT JSON/CSV files, WGS84 latitude/longitude, command-line flags).
* **Sun.** Azimuth ``az`` measured from south, positive toward **east**
  (PAINT's numbers, checked against an independent solar-position code);
  elevation ``el`` above the horizon. The unit vector pointing *to* the sun is
  ``(cos el sin az, -cos el cos az, sin el)``.
* **Incoming light** travels along ``-sun_direction``; reflection of a direction
  ``d`` at a unit normal ``n`` is ``d - 2 (d . n) n``.
* **Heliostat body frame.** At zero joint angles the mirror normal is PAINT's
  ``initial_orientation`` (south, ``(0, -1, 0)``) and the body axes coincide
  with ENU. Facet / surface data (deflectometry, canting) are given in a
  *surface frame* whose normal is ``+z`` (mirror lying face up, ``x`` = east,
  ``y`` = north). A pose's ``rotation`` maps surface-frame vectors to ENU, so
  ``rotation @ (0, 0, 1)`` is the mirror normal (see ``heliojax._kinematics``).
* **Targets** are planar rectangles given by their corner points. In-target
  coordinates ``(u, v)`` are metres from the target centre along ``u_axis``
  (from the "left" corners to the "right" corners as PAINT names them, i.e.
  left/right as seen by an observer facing the target) and ``v_axis`` (from
  lower to upper corners, made orthogonal to ``u_axis``). The plane normal is
  ``u_axis x v_axis`` and points toward the observer (the heliostat field).

Precision: geodesy and calibration need float64. heliojax never flips
``jax_enable_x64`` at import; the CLI and the test-suite enable it
(``jax.config.update("jax_enable_x64", True)``) and library functions compute
in the dtype of their inputs. In float32 an ENU coordinate 200 m from the
origin is resolved to ~1e-5 m, but ECEF coordinates (~6e6 m) only to ~0.5 m,
so the WGS84 conversions require float64.
"""

from __future__ import annotations

import functools
import typing
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Bool, Float

from ._programs import cached_jit

# WGS84 ellipsoid (NIMA TR8350.2).
WGS84_A = 6378137.0
"""Semi-major axis in metres."""
WGS84_F = 1.0 / 298.257223563
"""Flattening."""
MAX_FIELD_EXTENT_M = 20_000.0
"""Largest distance (m) of a point of a plant (a heliostat, an aim point) from its
field's origin: the largest fields reach about 2 km; a point farther away in an input
file is a data error (``heliojax accept``'s field CSV, ``heliojax aim --aim-csv``)."""
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""
_WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)


def _warn_if_single_precision(x: Array, function: str) -> None:
    """Warn (per call; at trace time under ``jit``) when geodesy runs in less than
    float64: Earth-centred coordinates (~6.4e6 m) resolve only ~0.5 m in float32, so
    positions come out decimetres off without an error (``hj.wgs84_to_enu`` of a point
    10 m from the origin: ~0.1 m per axis)."""
    if jnp.issubdtype(x.dtype, jnp.floating) and jnp.finfo(x.dtype).bits < 64:
        warnings.warn(
            f"{function}: geodesy in {x.dtype} resolves Earth-centred coordinates only to "
            f"~{float(np.spacing(np.asarray(WGS84_A, x.dtype))):.1g} m; enable float64 "
            '(jax.config.update("jax_enable_x64", True)) for positions to the millimetre',
            stacklevel=3,
        )


def _check_triples(
    function: str, name: str, x: Array, *, one: bool = False, geodetic: bool = False, vectors: bool = False
) -> None:
    """ValueError naming ``name`` (an argument of ``function``) when ``x``'s last axis
    is not 3 (``one``: when ``x`` is not one ``(3,)`` vector; ``vectors``: the message
    asks for directions, not points in metres), and, for a concrete
    geodetic ``[lat_deg, lon_deg, alt_m]`` (``geodetic``), when a latitude lies outside
    [-90, 90] degrees. JAX clamps an index past the end: ``lla[..., 2]`` of a
    ``(lat, lon)`` pair had read the longitude as the altitude, without an error. The
    shape is checked under ``jit`` and ``vmap`` too (it is static); values only where
    concrete (NaN passes: NaN out)."""
    shape = jnp.shape(x)
    if (shape != (3,)) if one else (len(shape) == 0 or shape[-1] != 3):
        what = "one (3,) vector" if one else "(..., 3) points"
        unit = "[lat_deg, lon_deg, alt_m]" if geodetic else "metres"
        expected = "(..., 3) ENU vectors" if vectors else f"{what}, {unit}"
        raise ValueError(f"{function}: {name} has shape {shape}; expected {expected}")
    if geodetic and not isinstance(x, Tracer):
        lat = np.asarray(x)[..., 0]
        if np.any(np.abs(lat) > 90.0):
            worst = float(lat.flat[int(np.argmax(np.where(np.isnan(lat), 0.0, np.abs(lat))))])
            raise ValueError(
                f"{function}: {name} holds a latitude of {worst:g} deg, outside [-90, 90] "
                "(expected [lat_deg, lon_deg, alt_m]: swapped, or not degrees?)"
            )


def wgs84_to_ecef(lla: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """WGS84 geodetic ``[lat_deg, lon_deg, alt_m]`` -> Earth-centred Earth-fixed metres.
    Warns below float64 (see :func:`_warn_if_single_precision`).

    Args:
        lla: ``(..., 3)`` latitude (deg), longitude (deg), ellipsoidal height (m).

    Returns:
        ``(..., 3)`` ECEF coordinates in metres.

    Raises:
        ValueError: ``lla`` not ``(..., 3)``, or a (concrete) latitude outside [-90, 90]
            degrees.
    """
    lla = jnp.asarray(lla)
    _check_triples("wgs84_to_ecef", "lla", lla, geodetic=True)
    _warn_if_single_precision(lla, "wgs84_to_ecef")
    return _wgs84_to_ecef(lla)


def _wgs84_to_ecef(lla: Array) -> Array:
    lat = jnp.deg2rad(lla[..., 0])
    lon = jnp.deg2rad(lla[..., 1])
    h = lla[..., 2]
    sin_lat, cos_lat = jnp.sin(lat), jnp.cos(lat)
    n = WGS84_A / jnp.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    x = (n + h) * cos_lat * jnp.cos(lon)
    y = (n + h) * cos_lat * jnp.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sin_lat
    return jnp.stack([x, y, z], axis=-1)


def ecef_to_wgs84(xyz: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """ECEF metres -> WGS84 ``[lat_deg, lon_deg, alt_m]``.

    Bowring's parametric-latitude start followed by three Newton-type
    refinements; exact to well below a micrometre for points within a few
    hundred kilometres of the ellipsoid surface (in float64; warns below it).

    Args:
        xyz: ``(..., 3)`` ECEF coordinates in metres.

    Returns:
        ``(..., 3)`` latitude (deg), longitude (deg), ellipsoidal height (m).
    """
    xyz = jnp.asarray(xyz)
    _check_triples("ecef_to_wgs84", "xyz", xyz)
    _warn_if_single_precision(xyz, "ecef_to_wgs84")
    return _ecef_to_wgs84(xyz)


def _ecef_to_wgs84(xyz: Array) -> Array:
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    lon = jnp.arctan2(y, x)
    p = jnp.hypot(x, y)
    beta = jnp.arctan2(z * WGS84_A, p * WGS84_B)
    lat = jnp.arctan2(
        z + _WGS84_EP2 * WGS84_B * jnp.sin(beta) ** 3,
        p - WGS84_E2 * WGS84_A * jnp.cos(beta) ** 3,
    )
    for _ in range(3):
        beta = jnp.arctan2((1.0 - WGS84_F) * jnp.sin(lat), jnp.cos(lat))
        lat = jnp.arctan2(
            z + _WGS84_EP2 * WGS84_B * jnp.sin(beta) ** 3,
            p - WGS84_E2 * WGS84_A * jnp.cos(beta) ** 3,
        )
    sin_lat = jnp.sin(lat)
    n = WGS84_A / jnp.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    # Height formula stable at all latitudes.
    h = p * jnp.cos(lat) + z * sin_lat - WGS84_A**2 / n
    return jnp.stack([jnp.rad2deg(lat), jnp.rad2deg(lon), h], axis=-1)


def _ecef_to_enu_matrix(origin_lla: Float[ArrayLike, "3"]) -> Float[Array, "3 3"]:
    """Rows are the east, north and up unit vectors at ``origin_lla`` in ECEF."""
    origin_lla = jnp.asarray(origin_lla)
    lat = jnp.deg2rad(origin_lla[0])
    lon = jnp.deg2rad(origin_lla[1])
    sl, cl = jnp.sin(lat), jnp.cos(lat)
    so, co = jnp.sin(lon), jnp.cos(lon)
    zero = jnp.zeros_like(sl)
    return jnp.stack(
        [
            jnp.stack([-so, co, zero]),
            jnp.stack([-sl * co, -sl * so, cl]),
            jnp.stack([cl * co, cl * so, sl]),
        ]
    )


def wgs84_to_enu(lla: Float[ArrayLike, "... 3"], origin_lla: Float[ArrayLike, "3"]) -> Float[Array, "... 3"]:
    """WGS84 ``[lat_deg, lon_deg, alt_m]`` -> local ENU metres about ``origin_lla``.

    Args:
        lla: ``(..., 3)`` points.
        origin_lla: ``(3,)`` the frame origin (PAINT: ``power_plant_properties.coordinates``).

    Returns:
        ``(..., 3)`` east, north, up in metres (warns below float64, see
        :func:`wgs84_to_ecef`).

    Raises:
        ValueError: ``lla`` not ``(..., 3)`` or ``origin_lla`` not ``(3,)`` (also under
            ``jit``), or a (concrete) latitude outside [-90, 90] degrees.
    """
    lla, origin_lla = jnp.asarray(lla), jnp.asarray(origin_lla)
    _check_triples("wgs84_to_enu", "lla", lla, geodetic=True)
    _check_triples("wgs84_to_enu", "origin_lla", origin_lla, one=True, geodetic=True)
    rot = _ecef_to_enu_matrix(origin_lla)
    ecef = _wgs84_to_ecef(lla)
    _warn_if_single_precision(ecef, "wgs84_to_enu")
    d = ecef - jnp.broadcast_to(_wgs84_to_ecef(origin_lla), ecef.shape)
    return d @ rot.T


def enu_to_wgs84(enu: Float[ArrayLike, "... 3"], origin_lla: Float[ArrayLike, "3"]) -> Float[Array, "... 3"]:
    """Local ENU metres about ``origin_lla`` -> WGS84 ``[lat_deg, lon_deg, alt_m]``.

    Inverse of :func:`wgs84_to_enu` (round trip better than 1e-6 m in float64; warns
    below it).
    """
    enu, origin_lla = jnp.asarray(enu), jnp.asarray(origin_lla)
    _check_triples("enu_to_wgs84", "enu", enu)
    _check_triples("enu_to_wgs84", "origin_lla", origin_lla, one=True, geodetic=True)
    rot = _ecef_to_enu_matrix(origin_lla)
    ecef = enu @ rot
    ecef = ecef + jnp.broadcast_to(_wgs84_to_ecef(origin_lla), ecef.shape)
    _warn_if_single_precision(ecef, "enu_to_wgs84")
    return _ecef_to_wgs84(ecef)


def normalize(v: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """``v / |v|`` along the last axis."""
    v = jnp.asarray(v)
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def sun_direction(azimuth: Float[ArrayLike, "..."], elevation: Float[ArrayLike, "..."]) -> Float[Array, "... 3"]:
    """Unit ENU vector pointing to the sun.

    Args:
        azimuth: rad, 0 = south, positive toward east (PAINT convention).
        elevation: rad above the horizon.

    Returns:
        ``(..., 3)`` ``(cos el sin az, -cos el cos az, sin el)``.
    """
    az = jnp.asarray(azimuth)
    el = jnp.asarray(elevation)
    ce = jnp.cos(el)
    return jnp.stack([ce * jnp.sin(az), -ce * jnp.cos(az), jnp.sin(el)], axis=-1)


@functools.partial(cached_jit, quick=True)  # one program, not one per operation, outside a jitted function
def direction_to_azimuth_elevation(
    direction: Float[ArrayLike, "... 3"],
) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """Inverse of :func:`sun_direction`: ``(azimuth, elevation)`` in rad of a unit vector.

    Raises:
        ValueError: ``direction``'s last axis is not 3 (a ``(2,)`` vector had given an
            azimuth and elevation without an error: JAX clamps the index past its end)."""
    d = jnp.asarray(direction)
    _check_triples("direction_to_azimuth_elevation", "direction", d, vectors=True)
    az = jnp.arctan2(d[..., 0], -d[..., 1])
    el = jnp.arctan2(d[..., 2], jnp.hypot(d[..., 0], d[..., 1]))
    return az, el


def reflect(direction: Float[ArrayLike, "... 3"], normal: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """Mirror reflection ``d - 2 (d . n) n`` of a propagation direction at unit normal ``n``
    (ValueError for a last axis other than 3)."""
    d = jnp.asarray(direction)
    n = jnp.asarray(normal)
    _check_triples("reflect", "direction", d, vectors=True)
    _check_triples("reflect", "normal", n, vectors=True)
    return d - 2.0 * jnp.sum(d * n, axis=-1, keepdims=True) * n


def bisector_normal(sun: Float[ArrayLike, "... 3"], to_target: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """Mirror normal that reflects light from direction ``sun`` (unit, pointing to the
    sun) into direction ``to_target`` (unit): the normalised bisector."""
    return normalize(jnp.asarray(sun) + jnp.asarray(to_target))


def angle_between(a: Float[ArrayLike, "... 3"], b: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
    """Angle in rad between two vectors, accurate for tiny angles (atan2 form)
    (ValueError for a last axis other than 3)."""
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    _check_triples("angle_between", "a", a, vectors=True)
    _check_triples("angle_between", "b", b, vectors=True)
    cross = jnp.linalg.norm(jnp.cross(a, b), axis=-1)
    return jnp.arctan2(cross, jnp.sum(a * b, axis=-1))


@typing.final
class TargetPlane(eqx.Module):
    """A planar rectangular target (a calibration target or a receiver aperture).

    Attributes:
        centre: ``(3,)`` ENU m, centre of the rectangle.
        normal: ``(3,)`` unit normal, ``u_axis x v_axis``, facing the field.
        u_axis: ``(3,)`` unit in-plane axis from the left to the right edge.
        v_axis: ``(3,)`` unit in-plane axis from the lower to the upper edge.
        half_width: m, half extent along ``u_axis``.
        half_height: m, half extent along ``v_axis``.
    """

    centre: Float[Array, "3"]
    normal: Float[Array, "3"]
    u_axis: Float[Array, "3"]
    v_axis: Float[Array, "3"]
    half_width: Float[Array, ""]
    half_height: Float[Array, ""]

    @classmethod
    def from_corners(
        cls,
        upper_left: Float[ArrayLike, "3"],
        upper_right: Float[ArrayLike, "3"],
        lower_left: Float[ArrayLike, "3"],
        lower_right: Float[ArrayLike, "3"],
    ) -> TargetPlane:
        """Build the plane from four ENU corner points (m).

        The centre is the mean of the corners; ``u_axis`` runs from the mean of
        the left corners to the mean of the right ones; ``v_axis`` is the
        lower-to-upper direction made orthogonal to ``u_axis`` (Gram-Schmidt);
        the normal is ``u_axis x v_axis``. No assumption of a vertical or
        axis-aligned target is made.

        Raises:
            ValueError: a corner not of shape ``(3,)`` (also under ``jit``), or (concrete)
                corners that span no rectangle: not finite, or no width or height (they
                had given a plane of NaN axes, which every ray missed without an error).
        """
        ul, ur, ll, lr = (jnp.asarray(p) for p in (upper_left, upper_right, lower_left, lower_right))
        names = ("upper_left", "upper_right", "lower_left", "lower_right")
        for name, corner in zip(names, (ul, ur, ll, lr), strict=True):
            if corner.shape != (3,):
                raise ValueError(f"TargetPlane.from_corners: {name} has shape {corner.shape}; expected (3,), ENU m")
        centre = (ul + ur + ll + lr) / 4.0
        width_vec = (ur + lr) / 2.0 - (ul + ll) / 2.0
        height_vec = (ul + ur) / 2.0 - (ll + lr) / 2.0
        u_axis = normalize(width_vec)
        v_raw = height_vec - jnp.dot(height_vec, u_axis) * u_axis
        v_axis = normalize(v_raw)
        normal = jnp.cross(u_axis, v_axis)
        if not any(isinstance(x, Tracer) for x in (ul, ur, ll, lr)):
            width, height = (float(np.linalg.norm(np.asarray(x))) for x in (width_vec, v_raw))  # no eager XLA op
            if not (np.isfinite(np.asarray(normal)).all() and width > 0.0 and height > 0.0):
                raise ValueError(
                    "TargetPlane.from_corners: the corners span no rectangle "
                    f"(width {width:g} m, height {height:g} m); expected four finite corners in the order "
                    "upper_left, upper_right, lower_left, lower_right"
                )
        return cls(
            centre=centre,
            normal=normal,
            u_axis=u_axis,
            v_axis=v_axis,
            half_width=jnp.linalg.norm(width_vec) / 2.0,
            half_height=jnp.linalg.norm(v_raw) / 2.0,
        )

    def to_plane(self, point: Float[ArrayLike, "... 3"]) -> Float[Array, "... 2"]:
        """In-target coordinates ``(u, v)`` in metres of ENU points (projected on the plane)."""
        point, centre = jnp.broadcast_arrays(jnp.asarray(point), self.centre)
        d = point - centre
        return jnp.stack([d @ self.u_axis, d @ self.v_axis], axis=-1)

    def from_plane(self, uv: Float[ArrayLike, "... 2"]) -> Float[Array, "... 3"]:
        """ENU points of in-target coordinates ``(u, v)`` in metres."""
        uv = jnp.asarray(uv)
        lead = (1,) * (uv.ndim - 1)
        u_axis, v_axis, centre = (x.reshape(lead + (3,)) for x in (self.u_axis, self.v_axis, self.centre))
        return centre + uv[..., :1] * u_axis + uv[..., 1:2] * v_axis


@typing.final
class PlaneHit(eqx.Module):
    """Result of :func:`intersect_plane`.

    Attributes:
        point: ``(..., 3)`` ENU m, intersection with the infinite plane (NaN-free;
            meaningless where the ray is parallel to the plane).
        uv: ``(..., 2)`` in-target coordinates of ``point`` in m.
        distance: ``(...)`` ray parameter ``t`` (m for a unit direction).
        hit: ``(...)`` True where ``t > 0``, the ray meets the front face and the
            point lies inside the rectangle.
    """

    point: Float[Array, "... 3"]
    uv: Float[Array, "... 2"]
    distance: Float[Array, "..."]
    hit: Bool[Array, "..."]


def intersect_plane(
    origin: Float[ArrayLike, "... 3"],
    direction: Float[ArrayLike, "... 3"],
    target: TargetPlane,
) -> PlaneHit:
    """Intersect rays ``origin + t * direction`` with a target plane.

    Broadcasts over leading axes of ``origin`` and ``direction``; vmap over
    targets (a batched ``TargetPlane``) with ``jax.vmap``.

    Args:
        origin: ``(..., 3)`` ENU m.
        direction: ``(..., 3)`` propagation directions (need not be unit).
        target: the plane.

    Returns:
        A :class:`PlaneHit`.
    """
    o, d = jnp.broadcast_arrays(jnp.asarray(origin), jnp.asarray(direction))
    denom = d @ target.normal
    front = denom < 0.0
    safe = jnp.where(jnp.abs(denom) > 1e-300, denom, jnp.ones_like(denom))
    t = ((jnp.broadcast_to(target.centre, o.shape) - o) @ target.normal) / safe
    point = o + t[..., None] * d
    uv = target.to_plane(point)
    inside = (jnp.abs(uv[..., 0]) <= target.half_width) & (jnp.abs(uv[..., 1]) <= target.half_height)
    hit = front & (t > 0.0) & inside & (jnp.abs(denom) > 1e-300)
    return PlaneHit(point=point, uv=uv, distance=t, hit=hit)


def products_by_reduction() -> bool:
    """Whether the small products of the hot paths (:func:`matmul3`, :func:`matvec3`,
    the fit's Jacobian-vector products) are written as multiply-and-reduce instead of
    ``dot``: on accelerators yes, on CPU no. Decided when a function is traced, from
    JAX's default backend (as :func:`heliojax.fitting.default_solver` decides the LM
    step).

    Why: vmapped over heliostats and records (and transposed by reverse-mode
    differentiation) a 3 x 3 ``dot`` becomes a batched GEMM. On an H200 these ran as
    Triton GEMM kernels that took 1.5 of the 2.3 s of a 100,000 x 100 fit; as
    multiply-and-reduce they fuse into the surrounding kernels (0.43-0.47 s; README,
    Benchmarks). On CPU the reverse holds: XLA's small-``dot`` emitter fits
    1,000 x 100 in 0.94 s, multiply-and-reduce in 2.0 s (one run each).
    """
    return jax.default_backend() != "cpu"


def matmul3(a: Float[Array, "3 3"], b: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """``a @ b`` for two ``(3, 3)`` matrices; on accelerators as multiply-and-reduce
    (see :func:`products_by_reduction`; the same numbers up to summation order)."""
    if products_by_reduction():
        return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)
    return a @ b


def matvec3(a: Float[Array, "3 3"], v: Float[Array, "3"]) -> Float[Array, "3"]:
    """``a @ v`` for a ``(3, 3)`` matrix and a ``(3,)`` vector; on accelerators as
    multiply-and-reduce (see :func:`products_by_reduction`)."""
    if products_by_reduction():
        return jnp.sum(a * v[None, :], axis=1)
    return a @ v


def rotation_about_axis(axis: Float[ArrayLike, "3"], angle: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """Right-handed rotation matrix by ``angle`` (rad) about unit ``axis`` (Rodrigues)."""
    k = normalize(jnp.asarray(axis))
    angle = jnp.asarray(angle)
    kx = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=k.dtype)
    eye = jnp.eye(3, dtype=k.dtype)
    return eye + jnp.sin(angle) * kx + (1.0 - jnp.cos(angle)) * (kx @ kx)


def rotation_x(angle: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """Right-handed rotation about east (x) by ``angle`` rad."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([one, zero, zero]), jnp.stack([zero, c, -s]), jnp.stack([zero, s, c])])


def rotation_y(angle: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """Right-handed rotation about north (y) by ``angle`` rad."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, zero, s]), jnp.stack([zero, one, zero]), jnp.stack([-s, zero, c])])


def rotation_z(angle: Float[ArrayLike, ""]) -> Float[Array, "3 3"]:
    """Right-handed rotation about up (z) by ``angle`` rad."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    one, zero = jnp.ones_like(c), jnp.zeros_like(c)
    return jnp.stack([jnp.stack([c, -s, zero]), jnp.stack([s, c, zero]), jnp.stack([zero, zero, one])])


UNIT_TOLERANCE = 1e-6
"""Largest ``| |v| - 1 |`` of a direction given as a unit vector (sun vectors)."""


def check_numeric(x: typing.Any, name: str, expected: str, *, bools: bool = True) -> None:
    """TypeError naming ``name`` where ``x`` is not an array of numbers (a string,
    None, an object array, complex numbers; booleans too unless ``bools``): JAX's own
    error is many frames deep and names no argument, and ``True`` had been read as 1.
    Skipped for traced values."""
    if isinstance(x, Tracer):
        return
    kind = "?"
    if x is not None and not isinstance(x, (str, bytes)):
        try:
            kind = np.asarray(x).dtype.kind
        except (TypeError, ValueError):  # a ragged list
            kind = "?"
    if kind not in ("biuf" if bools else "iuf"):
        raise TypeError(f"{name}: expected {expected}, got {type(x).__name__} {str(x)[:40]!r}")


def check_unit_vectors(vectors: ArrayLike, used: ArrayLike | None, name: str) -> None:
    """ValueError naming ``name`` where a used vector (``used``: a mask of ``vectors``'
    leading shape; ``None``: all) is not a finite unit vector within
    :data:`UNIT_TOLERANCE`. Skipped under a JAX transformation (traced values).
    A sun vector of length 2 had calibrated to other parameters, "converged"."""
    if isinstance(vectors, Tracer) or isinstance(used, Tracer):
        return
    v = np.asarray(vectors, float)
    if v.ndim == 0 or v.shape[-1] != 3:
        raise ValueError(f"{name} has shape {v.shape}; expected (..., 3) unit ENU vectors")
    squared = np.einsum("...i,...i->...", v, v)  # no square root: |v|^2 - 1 ~ 2 (|v| - 1)
    bad = ~(np.abs(squared - 1.0) <= 2.0 * UNIT_TOLERANCE)
    if used is not None:
        bad &= np.broadcast_to(np.asarray(used, bool), bad.shape)
    if bad.any():
        first = np.sqrt(squared[bad].flat[0])
        raise ValueError(
            f"{name}: {int(bad.sum())} vector(s) are not finite unit vectors (e.g. length {first:.6g}); "
            "sun vectors are unit ENU directions towards the sun (heliojax.sun_direction)"
        )


__all__ = [
    "MAX_FIELD_EXTENT_M",
    "UNIT_TOLERANCE",
    "PlaneHit",
    "TargetPlane",
    "WGS84_A",
    "WGS84_F",
    "angle_between",
    "bisector_normal",
    "check_numeric",
    "check_unit_vectors",
    "direction_to_azimuth_elevation",
    "ecef_to_wgs84",
    "enu_to_wgs84",
    "intersect_plane",
    "matmul3",
    "matvec3",
    "normalize",
    "products_by_reduction",
    "reflect",
    "rotation_about_axis",
    "rotation_x",
    "rotation_y",
    "rotation_z",
    "sun_direction",
    "wgs84_to_ecef",
    "wgs84_to_enu",
]
