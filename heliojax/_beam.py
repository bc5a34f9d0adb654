"""Measured quantities and the beam pointing error metric (the calibration residuals)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._geometry import angle_between, bisector_normal, intersect_plane, normalize, reflect
from ._heliostat import Pose


def measured_normal(
    centre: Float[ArrayLike, "3"], sun: Float[ArrayLike, "3"], focal_spot: Float[ArrayLike, "3"]
) -> Float[Array, "3"]:
    """Normal implied by a record: bisector of the sun direction and the unit vector
    from the mirror centre to the measured focal spot (all ENU)."""
    return bisector_normal(sun, normalize(jnp.asarray(focal_spot) - jnp.asarray(centre)))


def reflected_ray(pose: Pose, sun: Float[ArrayLike, "3"]) -> Float[Array, "3"]:
    """Direction of the central ray reflected at ``pose`` for sunlight from ``sun``."""
    return reflect(-jnp.asarray(sun), pose.normal)


def tangent_basis(r: Float[Array, "3"]) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """The beam error's axes about the unit ray ``r`` (ENU): ``e1 = normalize(up x r)``
    (horizontal) and ``e2 = r x e1`` (upward). Undefined (NaN) for a vertical ``r``,
    which no heliostat reflects toward a target; :func:`heliojax.optics.tangent_basis`
    is the ray tracer's basis, which turns to north-based axes near vertical."""
    up = jnp.asarray([0.0, 0.0, 1.0], r.dtype)
    e1 = normalize(jnp.cross(up, r))
    e2 = jnp.cross(r, e1)
    return e1, e2


def beam_error_components(
    pose: Pose, sun: Float[ArrayLike, "3"], focal_spot: Float[ArrayLike, "3"]
) -> Float[Array, "2"]:
    """The beam pointing error's two tangent-plane components (rad).

    With ``r`` the model's reflected central ray and ``d`` the unit vector from the
    model's mirror centre to the measured focal spot, the components are
    ``(d . e1, d . e2)`` with ``e1 = normalize(up x r)`` (horizontal) and
    ``e2 = r x e1`` (upward). Their norm is ``sin`` of the beam pointing error
    (equal to the angle to 1e-7 relative below 1 mrad); they are smooth
    everywhere and are the calibration residuals.
    """
    r = reflected_ray(pose, sun)
    d = normalize(jnp.asarray(focal_spot) - pose.centre)
    e1, e2 = tangent_basis(r)
    return jnp.stack([jnp.sum(d * e1, axis=-1), jnp.sum(d * e2, axis=-1)])


def beam_pointing_error(pose: Pose, sun: Float[ArrayLike, "3"], focal_spot: Float[ArrayLike, "3"]) -> Float[Array, ""]:
    """Beam pointing error in rad: the angle between the model's reflected central
    ray and the direction from the model's mirror centre to the measured focal spot.
    Multiply by 1e3 for mrad."""
    r = reflected_ray(pose, sun)
    d = jnp.asarray(focal_spot) - pose.centre
    return angle_between(r, d)


def target_miss_distance(
    pose: Pose, sun: Float[ArrayLike, "3"], focal_spot: Float[ArrayLike, "3"], target
) -> Float[Array, ""]:
    """Distance in m, on the target plane, between where the model's central ray hits
    the (infinite) plane of ``target`` and the measured focal spot."""
    r = reflected_ray(pose, sun)
    hit = intersect_plane(pose.centre, r, target)
    return jnp.linalg.norm(hit.point - jnp.asarray(focal_spot), axis=-1)


__all__ = [
    "beam_error_components",
    "beam_pointing_error",
    "measured_normal",
    "reflected_ray",
    "tangent_basis",
    "target_miss_distance",
]
