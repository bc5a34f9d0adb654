"""Monte Carlo flux tracing onto planar targets.

Model
=====

Every surface point ``i`` (a :class:`SurfacePoints` sample with area ``A_i``)
emits ``K = rays_per_point * steps`` rays. Ray ``k`` comes from the sun
direction ``d_k`` drawn from the sun shape about the central direction ``s``;
at the aligned point ``o_i = centre + R p_i`` with normal ``n_i = R m_i`` it is
reflected, ``r = -d_k + 2 (d_k . n_i) n_i``, intersected with the target plane
and splatted bilinearly into the flux image. Its power is

    P_ik = DNI * A_i * max(d_k . n_i, 0) * reflectivity / K          [W]

(the cosine of incidence is evaluated per ray and per point), so the image
integrates to ``DNI * reflectivity * sum_i A_i <cos_i>`` when the target catches
everything. Rays travelling away from the plane or hitting its back get no
power. Flux images are in W/m^2.

Image convention (:class:`ImageGrid`): an image is ``(ny, nx)`` with row 0 at
the top (largest ``v``) and column 0 at the left (smallest ``u``) of the
target's in-plane coordinates (``u`` from the "left" to the "right" corners as
PAINT names them, ``v`` upward) — the orientation of PAINT's flux PNGs. Pixel
``(r, c)`` has its centre at ``u = u_min + (c + 1/2) du``, ``v = v_max - (r + 1/2) dv``.
Bilinear splatting distributes a ray over the four nearest pixel centres (it
preserves the centroid exactly and adds ``du^2 / 6`` to the variance); rays
whose four neighbours fall outside the grid are lost.

Performance
===========

* Precision: the tracer computes in ``dtype`` (float32 by default; inputs are
  cast), whatever ``jax_enable_x64`` says.
* Per point, the reflected directions of the three basis vectors ``(s, e1, e2)``
  are projected once on the target frame, so a ray costs a 3x3 product, one
  division and a 4-wide scatter (one scatter per ray into a ``(cells, 4)``
  buffer, summed into pixels at the end).
* Memory: rays are generated in ``steps`` chunks of ``rays_per_point`` per point
  under ``lax.scan`` with fresh keys (``fold_in(key, step)``); only the
  accumulation buffer is carried, and each step is rematerialised under reverse
  mode, so memory is ``O(points * rays_per_point + pixels)`` independent of
  the total number of rays.
* Heliostats are batched by ``vmap`` over padded :class:`SurfacePoints` (zero-area
  points carry no power); with ``combine=True`` all heliostats share one target
  grid and their flux is summed into one image.
* Differentiable with respect to the surface points, normals and areas (hence
  NURBS control points), the pose (hence kinematic parameters), the sun and
  the target.
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from .._geometry import TargetPlane, bisector_normal, normalize
from .._heliostat import Pose, known_values
from .._limits import count_problem
from ._sunshape import AbstractSunShape, tangent_basis, uniforms
from ._surfaces import SurfacePoints


@typing.final
class ImageGrid(eqx.Module):
    """Pixel grid of a flux image on a target plane (in-plane metres).

    Attributes:
        u_min, u_max: m, left and right edges of the image along ``u_axis``.
        v_min, v_max: m, lower and upper edges along ``v_axis``.
        shape: ``(ny, nx)`` pixels (static).
    """

    u_min: Float[Array, "*b"]
    u_max: Float[Array, "*b"]
    v_min: Float[Array, "*b"]
    v_max: Float[Array, "*b"]
    shape: tuple[int, int] = eqx.field(static=True)

    def __check_init__(self):
        if len(self.shape) != 2 or any(count_problem(n, MAX_IMAGE_CELLS) for n in self.shape):
            raise ValueError(f"ImageGrid shape must be (ny, nx) >= 1, whole numbers, got {self.shape}")
        # checked where the edges are known (not under jit / vmap): a grid of negative
        # width had drawn a mirrored image, one of zero or NaN width an image of NaN
        for axis, lo, hi in (("u", self.u_min, self.u_max), ("v", self.v_min, self.v_max)):
            lo_, hi_ = known_values(lo), known_values(hi)
            if lo_ is None or hi_ is None:
                continue
            lo_, hi_ = np.broadcast_arrays(lo_, hi_)
            bad = ~(np.isfinite(lo_) & np.isfinite(hi_) & (hi_ > lo_))
            if bad.any():
                at = tuple(int(k) for k in np.argwhere(bad)[0])
                raise ValueError(
                    f"ImageGrid: {axis}_min < {axis}_max, both finite (m), needed; got {axis}_min = "
                    f"{float(lo_[at])}, {axis}_max = {float(hi_[at])}" + (f" at index {at}" if at else "")
                )

    @classmethod
    def for_target(cls, target: TargetPlane, shape: tuple[int, int] = (256, 256)) -> ImageGrid:
        """The grid covering the target rectangle exactly (PAINT flux PNG layout)."""
        return cls(
            u_min=-target.half_width,
            u_max=target.half_width,
            v_min=-target.half_height,
            v_max=target.half_height,
            shape=_pixels(shape),
        )

    @classmethod
    def centred(
        cls, u0: ArrayLike, v0: ArrayLike, width: ArrayLike, height: ArrayLike, shape: tuple[int, int] = (256, 256)
    ) -> ImageGrid:
        """A ``width x height`` (m) window centred at ``(u0, v0)``."""
        u0, v0, width, height = (jnp.asarray(x) for x in (u0, v0, width, height))
        return cls(
            u_min=u0 - width / 2,
            u_max=u0 + width / 2,
            v_min=v0 - height / 2,
            v_max=v0 + height / 2,
            shape=_pixels(shape),
        )

    @property
    def du(self) -> Float[Array, "*b"]:
        return (self.u_max - self.u_min) / self.shape[1]

    @property
    def dv(self) -> Float[Array, "*b"]:
        return (self.v_max - self.v_min) / self.shape[0]

    @property
    def pixel_area(self) -> Float[Array, "*b"]:
        return self.du * self.dv

    def pixel_centres(self) -> tuple[Float[Array, "*b nx"], Float[Array, "*b ny"]]:
        """``(u of each column, v of each row)`` in m (rows top to bottom)."""
        c = jnp.arange(self.shape[1], dtype=self.du.dtype) + 0.5
        r = jnp.arange(self.shape[0], dtype=self.dv.dtype) + 0.5
        lead = (1,) * jnp.ndim(self.du)
        u = self.u_min[..., None] + c.reshape(lead + (-1,)) * self.du[..., None]
        v = self.v_max[..., None] - r.reshape(lead + (-1,)) * self.dv[..., None]
        return u, v


def _pixels(shape: typing.Any) -> tuple[int, int]:
    """``shape`` as ``(ny, nx)``: whole numbers kept (NumPy integers as ints), others
    left for :class:`ImageGrid`'s check (2.5 had been cut to 2 pixels)."""
    return tuple(int(n) if isinstance(n, np.integer) else n for n in shape)  # pyright: ignore[reportReturnType]


def _check_image(function: str, image: typing.Any, grid: ImageGrid) -> None:
    """ValueError naming ``function`` unless ``image`` ends in ``grid.shape`` (a 1-D
    image had failed in JAX's axis handling, naming neither)."""
    if jnp.ndim(image) < 2 or tuple(jnp.shape(image)[-2:]) != tuple(grid.shape):
        raise ValueError(
            f"{function}: image has shape {jnp.shape(image)}; expected (..., ny, nx) = (..., *{grid.shape})"
        )


def centroid(image: Float[Array, "*b ny nx"], grid: ImageGrid) -> Float[Array, "*b 2"]:
    """Flux-weighted centroid ``(u, v)`` in m of an image on ``grid``."""
    _check_image("centroid", image, grid)
    u, v = (x.astype(image.dtype) for x in grid.pixel_centres())
    total = jnp.sum(image, axis=(-2, -1))
    safe = jnp.where(total > 0, total, 1.0)
    lift = lambda x: x.reshape((1,) * (image.ndim - x.ndim) + x.shape)  # noqa: E731
    cu = jnp.sum(image * lift(u[..., None, :]), axis=(-2, -1)) / safe
    cv = jnp.sum(image * lift(v[..., :, None]), axis=(-2, -1)) / safe
    return jnp.stack([cu, cv], axis=-1)


def total_power(image: Float[Array, "*b ny nx"], grid: ImageGrid) -> Float[Array, "*b"]:
    """Power in W of a flux image (sum of W/m^2 times the pixel area)."""
    _check_image("total_power", image, grid)
    return jnp.sum(image, axis=(-2, -1)) * grid.pixel_area


def plane_power(
    surface: SurfacePoints,
    pose: Pose,
    sun: Float[ArrayLike, "3"],
    target: TargetPlane,
    *,
    dni: float | ArrayLike = 1000.0,
    reflectivity: float | ArrayLike = 1.0,
) -> Float[Array, ""]:
    """Power in W that one heliostat reflects onto the front of ``target``'s plane,
    unbounded (not only its rectangle): ``dni`` (W/m^2) ``* reflectivity * sum_i A_i
    cos_i`` over the surface points (areas ``A_i`` in m^2) whose reflected ray of the
    sun's centre travels to the plane's front side (the tracer's rule per ray,
    :func:`flux_images`). What a flux image on that plane would integrate to if it
    were large enough (:func:`total_power` of the image is at most this, to the Monte
    Carlo noise); the sun shape's spread changes it only through rays grazing the plane
    and the mean cosine by a relative ``O(sigma^2)`` (1e-5 for 3 mrad).

    Raises:
        ValueError: (values known, not under ``jit``) a sun that is no direction (zero,
            NaN), a ``dni`` or ``reflectivity`` out of range: a power of 0, NaN or below
            zero had come back without a word.
    """
    check_directions("plane_power", "sun", sun)
    check_irradiance("plane_power", dni, reflectivity)
    return _plane_power(surface, pose, sun, target, dni, reflectivity)


@eqx.filter_jit
def _plane_power(surface, pose, sun, target, dni, reflectivity):
    dtype = jnp.asarray(pose.rotation).dtype  # the pose's precision (the surface is cast)
    rot = jnp.asarray(pose.rotation, dtype)
    o = jnp.asarray(pose.centre, dtype)[None] + jnp.asarray(surface.points, dtype) @ rot.T  # (p, 3) ENU m
    n = normalize(jnp.asarray(surface.normals, dtype) @ rot.T)
    s = normalize(jnp.asarray(sun, dtype))
    cosi = n @ s  # (p,)
    reflected = 2.0 * cosi[:, None] * n - s[None]
    towards = reflected @ jnp.asarray(target.normal, dtype) < 0.0  # travels against the normal, to the front
    in_front = (o - jnp.asarray(target.centre, dtype)[None]) @ jnp.asarray(target.normal, dtype) > 0.0
    lit = (cosi > 0.0) & towards & in_front
    collected = jnp.sum(jnp.where(lit, jnp.asarray(surface.areas, dtype) * cosi, 0.0))
    return jnp.asarray(dni, dtype) * jnp.asarray(reflectivity, dtype) * collected


def _float_array(x: ArrayLike) -> Array:
    """``x`` as a JAX array of its float dtype, integers as JAX's default float: the
    other vectors take its dtype (a centre of whole metres had cast the sun and the
    normal to integers, a NaN pose)."""
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(jnp.result_type(float))


def check_directions(function: str, name: str, v: typing.Any, *, shapes: str = "(3,)") -> None:
    """ValueError naming ``function`` and ``name`` unless ``v`` is ``(..., 3)`` and, where
    its values are known (not under ``jit`` / ``vmap``), every row is finite and of
    non-zero length. The optics normalise such a direction: a zero or NaN one (a sun, a
    normal, an aim direction) had given a NaN pose or an image of zeros without a word."""
    shape = jnp.shape(v)
    if len(shape) == 0 or shape[-1] != 3:
        raise ValueError(f"{function}: {name} has shape {shape}; expected {shapes}, ENU")
    a = known_values(v)
    if a is None:
        return
    bad = ~(np.isfinite(a).all(axis=-1) & (np.abs(a).sum(axis=-1) > 0.0))
    if bad.any():
        row = a[tuple(np.argwhere(bad)[0])] if a.ndim > 1 else a
        raise ValueError(
            f"{function}: {name} is {row.tolist()}, no direction ({int(bad.sum())} of {bad.size} bad); expected a "
            "finite vector of non-zero length (ENU; it is normalised)"
        )


def check_irradiance(function: str, dni: typing.Any, reflectivity: typing.Any) -> None:
    """ValueError naming ``function`` unless the (known) ``dni`` is finite and >= 0
    W/m^2 and ``reflectivity`` in [0, 1]: a NaN or negative one had traced a NaN or
    negative flux. Traced values are not checked."""
    for name, value, high in (("dni", dni, np.inf), ("reflectivity", reflectivity, 1.0)):
        if isinstance(value, jax.core.Tracer | jax.ShapeDtypeStruct):  # pyright: ignore[reportAttributeAccessIssue]
            continue
        v = None if isinstance(value, str | bytes) else known_values(value)
        if v is None or not np.all(np.isfinite(v) & (v >= 0) & (v <= high)):
            bound = "finite and >= 0 W/m^2" if name == "dni" else "in [0, 1]"
            raise ValueError(f"{function}: {name} must be {bound}, got {value!r}"[:200])


def _check_point(function: str, name: str, x: typing.Any) -> None:
    """ValueError naming ``function`` and ``name`` unless ``x`` is a ``(3,)`` point (ENU m)
    whose values, where known (not under ``jit``), are finite: a NaN point had given a
    pose of NaN, a ``(2,)`` one an error inside JAX."""
    if jnp.shape(x) != (3,):
        raise ValueError(f"{function}: {name} has shape {jnp.shape(x)}; expected (3,), ENU m")
    v = known_values(x)
    if v is not None and not np.isfinite(v).all():
        raise ValueError(f"{function}: {name} is {v.tolist()}; expected a finite point (ENU m)")


def aim_pose(centre: Float[ArrayLike, "3"], sun: Float[ArrayLike, "3"], aim_point: Float[ArrayLike, "3"]) -> Pose:
    """Ideal pose at ``centre`` (ENU m) reflecting the central sun ray onto ``aim_point``.

    The normal is the bisector; the surface ``x`` axis is kept horizontal
    (``up x normal``), as for an azimuth-elevation heliostat. For tests, the
    benchmark and what-if studies; real heliostats use :func:`heliojax.forward`.

    Raises:
        ValueError: an argument not of shape ``(3,)``, or (values known) a sun that is
            no direction (zero, NaN), an ``aim_point`` at ``centre`` or straight away
            from the sun (no mirror reflects the sun there): each had given a pose of
            NaN, which traced an image of zeros.
    """
    for name, x in (("centre", centre), ("aim_point", aim_point)):
        _check_point("aim_pose", name, x)
    check_directions("aim_pose", "sun", sun)
    if jnp.shape(sun) != (3,):
        raise ValueError(f"aim_pose: sun has shape {jnp.shape(sun)}; expected (3,), ENU")
    centre = _float_array(centre)
    sun = jnp.asarray(sun, centre.dtype)
    towards = jnp.asarray(aim_point, centre.dtype) - centre
    check_directions("aim_pose", "aim_point - centre", towards)
    s_, d_ = known_values(sun), known_values(towards)
    if s_ is not None and d_ is not None:
        bisector = s_ / np.linalg.norm(s_) + d_ / np.linalg.norm(d_)
        if not np.linalg.norm(bisector) > 1e-6:  # to rounding: a normal of rounding noise, or NaN
            raise ValueError(
                "aim_pose: aim_point lies straight away from the sun as seen from centre: no mirror reflects the "
                "sun there (the bisector of the sun and the aim direction is zero)"
            )
    normal = bisector_normal(sun, normalize(towards))
    return pose_from_normal(centre, normal)


def pose_from_normal(centre: Float[ArrayLike, "3"], normal: Float[ArrayLike, "3"]) -> Pose:
    """Pose with the given centre and unit normal, surface ``x`` axis horizontal
    (north-based if the normal is vertical).

    Raises:
        ValueError: ``centre`` not a finite ``(3,)`` point or ``normal`` no direction
            (zero, NaN; values known): a pose of NaN traced an image of zeros.
    """
    _check_point("pose_from_normal", "centre", centre)
    check_directions("pose_from_normal", "normal", normal)
    centre = _float_array(centre)
    normal = normalize(jnp.asarray(normal, centre.dtype))
    e1, e2 = tangent_basis(normal)
    rot = jnp.stack([e1, e2, normal], axis=-1)
    return Pose(normal=normal, centre=centre, rotation=rot)


# --------------------------------------------------------------------------------------
# The tracer
# --------------------------------------------------------------------------------------


MAX_UNIFORMS_PER_STEP = 2**32
"""Most uniform random numbers one step of :func:`flux_images` draws (heliostats x
points x ``rays_per_point`` x the sun shape's ``n_uniforms``): the range of the hash
generator's 32-bit counter, ~16 GiB of them in float32 (more steps trace more rays in
the same memory)."""
MAX_IMAGE_CELLS = 2**31 - 1
"""Most cells of :func:`flux_images`' accumulation buffer (one per pixel corner of
every image): its indices are 32-bit integers."""


@typing.final
class _Prepared(eqx.Module):
    """Per-point precomputation of one heliostat (all in the tracer dtype)."""

    coef: Float[Array, "p 3 3"]  # (output X in N,U,V) x (basis b in s,e1,e2): (R_i b) . X
    cosb: Float[Array, "p 3"]  # b . n_i
    h: Float[Array, " p"]  # (c - o_i) . N
    ou: Float[Array, " p"]  # (o_i - c) . U   (pixel units, shifted)
    ov: Float[Array, " p"]  # (o_i - c) . V   (pixel units, shifted)
    weight: Float[Array, " p"]  # DNI A_i rho / (K pixel_area)


def _prepare(surface, pose, sun, target, grid, scale, dtype):
    cast = lambda x: jnp.asarray(x).astype(dtype)  # noqa: E731
    rot = cast(pose.rotation)
    o = cast(pose.centre)[None] + cast(surface.points) @ rot.T
    n = cast(surface.normals) @ rot.T
    n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    s = cast(sun)
    s = s / jnp.linalg.norm(s)
    e1, e2 = tangent_basis(s)
    basis = jnp.stack([s, e1, e2])  # (3 b, 3)
    frame = jnp.stack([cast(target.normal), cast(target.u_axis), cast(target.v_axis)])  # (3 X, 3)
    bx = basis @ frame.T  # (b, X): b . X
    nx = n @ frame.T  # (p, X): n . X
    cosb = n @ basis.T  # (p, b): b . n
    # reflected propagation direction of incoming -b: -b + 2 (b.n) n ; projected on X.
    coef = -bx.T[None] + 2.0 * nx[:, :, None] * cosb[:, None, :]  # (p, X, b)
    c = cast(target.centre)
    h = (c[None] - o) @ frame[0]
    du, dv = cast(grid.du), cast(grid.dv)
    # continuous pixel coordinates: x = (u - u_min)/du - 1/2 ; y = (v_max - v)/dv - 1/2
    ou = ((o - c[None]) @ frame[1] - cast(grid.u_min)) / du - 0.5
    ov = (cast(grid.v_max) - (o - c[None]) @ frame[2]) / dv - 0.5
    weight = cast(surface.areas) * cast(scale) / (du * dv)
    # fold the pixel scaling of u, v into the coefficients
    coef = coef * jnp.stack([jnp.ones((), dtype), 1.0 / du, -1.0 / dv])[None, :, None]
    return _Prepared(coef=coef, cosb=cosb, h=h, ou=ou, ov=ov, weight=weight)


def _rays(prep: _Prepared, offsets: Float[Array, "p m 2"]):
    """Pixel coordinates and weights of the rays of one heliostat."""
    a, b = offsets[..., 0], offsets[..., 1]
    r2 = a * a + b * b
    # cos r and sin(r)/r by series: exact to float32 for r < 0.1 rad.
    c0 = 1.0 - r2 * (0.5 - r2 / 24.0)
    sinc = 1.0 - r2 * (1.0 / 6.0 - r2 / 120.0)
    c1, c2 = sinc * a, sinc * b
    k = prep.coef[:, :, None, :]  # (p, X, 1, b)
    dn = k[:, 0, :, 0] * c0 + k[:, 0, :, 1] * c1 + k[:, 0, :, 2] * c2
    dx = k[:, 1, :, 0] * c0 + k[:, 1, :, 1] * c1 + k[:, 1, :, 2] * c2
    dy = k[:, 2, :, 0] * c0 + k[:, 2, :, 1] * c1 + k[:, 2, :, 2] * c2
    cosi = prep.cosb[:, 0:1] * c0 + prep.cosb[:, 1:2] * c1 + prep.cosb[:, 2:3] * c2
    front = dn < 0.0
    t = prep.h[:, None] / jnp.where(front, dn, -1.0)
    ok = front & (t > 0.0) & (cosi > 0.0)
    x = prep.ou[:, None] + t * dx
    y = prep.ov[:, None] + t * dy
    w = jnp.where(ok, prep.weight[:, None] * cosi, 0.0)
    return x, y, w, ok


def _splat_indices(x, y, w, ok, shape):
    """Cell index into the ``((ny+1)(nx+1), 4)`` buffer and the 4 corner weights."""
    ny, nx = shape
    fx0 = jnp.floor(x)
    fy0 = jnp.floor(y)
    fx = x - fx0
    fy = y - fy0
    inside = ok & (fx0 >= -1) & (fx0 < nx) & (fy0 >= -1) & (fy0 < ny)
    ix = jnp.clip(fx0, -1, nx).astype(jnp.int32)
    iy = jnp.clip(fy0, -1, ny).astype(jnp.int32)
    idx = jnp.where(inside, (iy + 1) * (nx + 1) + (ix + 1), (ny + 1) * (nx + 1))
    gx = 1.0 - fx
    gy = 1.0 - fy
    w4 = jnp.stack([w * gx * gy, w * fx * gy, w * gx * fy, w * fx * fy], axis=-1)
    return idx, w4


def _buffer_to_image(buf, shape):
    ny, nx = shape
    b = buf.reshape(buf.shape[:-2] + (ny + 1, nx + 1, 4))
    return b[..., 1:, 1:, 0] + b[..., 1:, :-1, 1] + b[..., :-1, 1:, 2] + b[..., :-1, :-1, 3]


def flux_images(
    key: PRNGKeyArray,
    surfaces: SurfacePoints,
    poses: Pose,
    sun: Float[ArrayLike, "*b 3"],
    target: TargetPlane,
    grid: ImageGrid,
    sunshape: AbstractSunShape,
    *,
    rays_per_point: int = 16,
    steps: int = 1,
    first_step: Int[ArrayLike, ""] = 0,
    dni: float | ArrayLike = 1000.0,
    reflectivity: float | ArrayLike = 1.0,
    combine: bool = False,
    dtype=jnp.float32,
    rng: str = "hash",
) -> Float[Array, "*h ny nx"]:
    """Flux images (W/m^2) of one or several heliostats on planar targets.

    Args:
        key: PRNG key; the rays of step ``j`` use ``fold_in(key, first_step + j)``.
        surfaces: :class:`SurfacePoints` in the surface frame, ``(p, ...)`` for one
            heliostat or ``(h, p, ...)`` for a padded batch.
        poses: :class:`Pose` (``(3,)`` fields or batched ``(h, 3)``), e.g. from
            :func:`heliojax.forward`.
        sun: ``(3,)`` or ``(h, 3)`` unit vector(s) to the sun's centre, ENU.
        target: the target plane, shared or batched ``(h, ...)``.
        grid: image grid, shared or batched (``shape`` is common).
        sunshape: the sun's angular distribution.
        rays_per_point: rays per surface point per step (static).
        steps: number of ``lax.scan`` steps (static); total rays per point =
            ``rays_per_point * steps``.
        first_step: index of the first step. Pass it as an array (a Python int is a
            static argument and compiles a program per value): ``n`` calls with
            ``steps=s`` and ``first_step = 0, s, 2s, ...``, averaged, trace the same
            rays as one call with ``steps = n * s`` (e.g. to show progress).
        dni: direct normal irradiance, W/m^2.
        reflectivity: mirror reflectivity.
        combine: sum all heliostats into one image (shared target and grid).
        dtype: tracer precision (default float32).
        rng: ``"hash"`` (fast key-seeded counter hash) or ``"jax"`` (``jax.random.bits``);
            see :func:`heliojax.optics.uniforms`.

    Returns:
        ``(ny, nx)`` for one heliostat (or ``combine=True``), else ``(h, ny, nx)``.

    Raises:
        TypeError: ``dtype`` not a float type (an integer one had traced an image of zeros).
        ValueError: ``rays_per_point`` or ``steps`` not an integer >= 1 (0 had traced
            nothing and returned an image of zeros, as if no ray reached the target);
            surfaces of no points; (values known, not under ``jit``) a sun that is no
            direction (zero, NaN, inf), a pose of NaN, a ``dni`` or ``reflectivity``
            out of range (an array had not been checked): each had traced an image
            of zeros or NaN;
            more than :data:`MAX_UNIFORMS_PER_STEP` random numbers per step (trace in
            more steps) or more than :data:`MAX_IMAGE_CELLS` pixels of all images
            together: refused before any memory is taken.
    """
    for name, value in (("rays_per_point", rays_per_point), ("steps", steps)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
            raise ValueError(f"flux_images: {name} must be an integer >= 1, got {value!r}")
    h = 1 if surfaces.points.ndim == 2 else surfaces.points.shape[0]
    p = surfaces.points.shape[-2]
    if p == 0:
        raise ValueError("flux_images: surfaces hold no points (no ray to trace); sample the mirror first")
    draws = h * p * int(rays_per_point) * sunshape.n_uniforms
    if draws > MAX_UNIFORMS_PER_STEP:
        raise ValueError(
            f"flux_images: {h} heliostat(s) x {p} points x {rays_per_point} rays_per_point "
            f"need {draws:.3g} random numbers per step, more than {MAX_UNIFORMS_PER_STEP:.3g} (held in memory at "
            "once, and the counter of the hash generator would repeat): lower rays_per_point and raise steps"
        )
    pixels = (1 if combine else h) * (grid.shape[0] + 1) * (grid.shape[1] + 1)
    if pixels > MAX_IMAGE_CELLS:
        raise ValueError(
            f"flux_images: grid.shape {grid.shape} for {1 if combine else h} image(s) needs {pixels:.3g} cells, "
            f"more than {MAX_IMAGE_CELLS:.3g} (32-bit pixel indices): use fewer pixels"
        )
    if jnp.ndim(sun) not in (1, 2) or jnp.shape(sun)[-1] != 3:
        raise ValueError(f"flux_images: sun has shape {jnp.shape(sun)}; expected (3,) or (h, 3), unit ENU vectors")
    check_directions("flux_images", "sun", sun, shapes="(3,) or (h, 3)")
    check_irradiance("flux_images", dni, reflectivity)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"flux_images: dtype must be a float type (float32, float64), got {dtype!r}")
    for name, x in (("poses.centre", poses.centre), ("poses.rotation", poses.rotation)):
        v = known_values(x)
        if v is not None and not np.isfinite(v).all():
            raise ValueError(
                f"flux_images: {name} is not finite ({int((~np.isfinite(v)).sum())} NaN or inf value(s)); a pose "
                "of NaN (e.g. aimed at its own centre) traces no ray"
            )
    if combine and (jnp.ndim(target.centre) == 2 or jnp.ndim(grid.u_min) == 1):
        raise ValueError("combine=True needs one shared target and grid")
    options = {"rays_per_point": rays_per_point, "steps": steps, "first_step": first_step, "dni": dni}
    options |= {"reflectivity": reflectivity, "combine": combine, "dtype": dtype, "rng": rng}
    return _flux_images(key, surfaces, poses, sun, target, grid, sunshape, **options)


@eqx.filter_jit
def _flux_images(key, surfaces, poses, sun, target, grid, sunshape, **options) -> Float[Array, "*h ny nx"]:
    """:func:`flux_images` after its checks, compiled (``options``: its keyword arguments)."""
    rays_per_point, steps, first_step, dni = (options[k] for k in ("rays_per_point", "steps", "first_step", "dni"))
    reflectivity, combine, dtype, rng = (options[k] for k in ("reflectivity", "combine", "dtype", "rng"))
    single = surfaces.points.ndim == 2
    if single:
        surfaces = jax.tree_util.tree_map(lambda x: x[None], surfaces)
        poses = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], poses)
    h = surfaces.points.shape[0]
    sun = jnp.asarray(sun)
    sun_axis = 0 if sun.ndim == 2 else None
    target_axis = 0 if jnp.ndim(target.centre) == 2 else None
    grid_axis = 0 if jnp.ndim(grid.u_min) == 1 else None
    total_rays = rays_per_point * steps
    scale = jnp.asarray(dni) * jnp.asarray(reflectivity) / total_rays
    prep = jax.vmap(
        lambda s, p, sn, t, g: _prepare(s, p, sn, t, g, scale, dtype),
        in_axes=(0, 0, sun_axis, target_axis, grid_axis),
    )(surfaces, poses, sun, target, grid)
    shape = grid.shape
    ny, nx = shape
    cells = (ny + 1) * (nx + 1)
    p = surfaces.points.shape[1]
    n_img = 1 if combine else h

    def step_contribution(prep, k):
        u = uniforms(k, (h, p, rays_per_point, sunshape.n_uniforms), dtype, rng)
        # Barriers keep XLA from recomputing the ray chain once per consumer.
        offsets = jax.lax.optimization_barrier(sunshape.from_uniforms(u))
        x, y, w, ok = jax.lax.optimization_barrier(jax.vmap(_rays)(prep, offsets))
        idx, w4 = _splat_indices(x, y, w, ok, shape)
        if not combine:
            idx = jnp.where(idx < cells, idx + (jnp.arange(h, dtype=jnp.int32) * cells)[:, None, None], n_img * cells)
        buf = jnp.zeros((n_img * cells, 4), dtype)
        return buf.at[idx.reshape(-1)].add(w4.reshape(-1, 4), mode="drop")

    step_contribution = jax.checkpoint(step_contribution)

    def body(buf, j):
        return buf + step_contribution(prep, jax.random.fold_in(key, j)), None

    buf0 = jnp.zeros((n_img * cells, 4), dtype)
    first = jnp.asarray(first_step, jnp.int32)
    if steps == 1:
        buf = step_contribution(prep, jax.random.fold_in(key, first))
    else:
        buf, _ = jax.lax.scan(body, buf0, first + jnp.arange(steps, dtype=jnp.int32))
    image = _buffer_to_image(buf.reshape(n_img, cells, 4), shape)
    if single or combine:
        return image[0]
    return image


def flux_image(
    key: PRNGKeyArray,
    surface: SurfacePoints,
    pose: Pose,
    sun: Float[ArrayLike, "3"],
    target: TargetPlane,
    grid: ImageGrid,
    sunshape: AbstractSunShape,
    **kwargs,
) -> Float[Array, "ny nx"]:
    """Flux image (W/m^2) of one heliostat; see :func:`flux_images` for the arguments."""
    return flux_images(key, surface, pose, sun, target, grid, sunshape, **kwargs)


def ray_count(surfaces: SurfacePoints, rays_per_point: int, steps: int = 1) -> int:
    """Number of rays traced (padding points included); ValueError for
    ``rays_per_point`` or ``steps`` not a whole number >= 1 (-3 had counted -96 rays)."""
    for name, value in (("rays_per_point", rays_per_point), ("steps", steps)):
        problem = count_problem(value, MAX_UNIFORMS_PER_STEP)
        if problem is not None:
            raise ValueError(f"ray_count: {name} {problem}")
    return int(np.prod(surfaces.areas.shape)) * rays_per_point * steps


__all__ = [
    "MAX_IMAGE_CELLS",
    "MAX_UNIFORMS_PER_STEP",
    "ImageGrid",
    "aim_pose",
    "centroid",
    "flux_image",
    "flux_images",
    "plane_power",
    "pose_from_normal",
    "ray_count",
    "total_power",
]
