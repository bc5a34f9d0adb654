"""Heliostat geometry (actuators, axis offsets), record context, pose, and the
rotation chain shared by every kinematic model (:mod:`heliojax._kinematics`).

The chain (frames and signs, checked against the PAINT records)
--------------------------------------------------------------

All vectors are ENU (see :mod:`heliojax._geometry`). The heliostat *body frame*
coincides with ENU when the mirror normal equals PAINT's ``initial_orientation``
``n_ba = (0, -1, 0)`` (facing south). With ``Rx, Ry, Rz`` the right-handed
rotations about east, north and up::

    n   = R01 . Rx(theta - pi/2) . R12 . Rz(tau) . R2M . n_ba
    O_M = P + V01 + R01 . Rx(theta - pi/2) . (V12 + R12 . Rz(tau) . V2M)

    R01 = Ry(alpha) . Rz(beta)     two tilts of axis 1 (about north, about up)
    R12 = Ry(gamma)                non-orthogonality of axis 2 to axis 1
    R2M = Rx(delta)                tilt of the mirror about axis 1's direction

* **Axis 1** (nearest the ground) is horizontal east-west; its joint angle
  ``theta`` is the tilt of the mirror normal from the zenith toward the south:
  ``theta = 0`` faces up, ``theta = pi/2`` faces south (``n_ba``). PAINT's
  actuator angles of axis 1 (``initial_angle`` ~0.01 rad at count 0, up to
  ``max_movement_angle`` = pi/2) are exactly this ``theta``; hence the
  ``- pi/2`` that brings the south-facing reference pose to ``theta = pi/2``.
* **Axis 2** rides on axis 1 and turns the mirror about the body's up axis
  (the tilted up axis); ``tau > 0`` turns the normal toward east.
* ``P`` is ``heliostat_position``; ``V01``, ``V12``, ``V2M`` are PAINT's
  ``joint_translation_*_1``, ``joint_translation_*_2`` and
  ``concentrator_translation_*`` (e, n, u), each expressed in the body frame of
  its joint, i.e. in ENU at the south-facing reference pose.
* The surface frame of facets and deflectometry (mirror face up, normal +z)
  maps to the body frame by ``Rx(pi/2)``; :class:`Pose` ``.rotation`` is the
  full surface-to-ENU rotation.

"""

from __future__ import annotations

import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._geometry import check_numeric, matmul3, matvec3, rotation_x, rotation_y, rotation_z

_HALF_PI = np.pi / 2.0
N_BA = (0.0, -1.0, 0.0)
"""Mirror normal in the body frame at the reference pose (PAINT ``initial_orientation``)."""


# --------------------------------------------------------------------------------------
# Geometry measured once per heliostat
# --------------------------------------------------------------------------------------


def _actuator_psi(stroke, offset, pivot_radius):
    cos_psi = (offset**2 + pivot_radius**2 - stroke**2) / (2.0 * offset * pivot_radius)
    return jnp.arccos(jnp.clip(cos_psi, -1.0, 1.0))


def _broadcasts_to(shape: tuple[int, ...], target: tuple[int, ...]) -> bool:
    """Whether an array of ``shape`` broadcasts to ``target`` (``jnp.broadcast_to``)."""
    try:
        return np.broadcast_shapes(shape, target) == target
    except ValueError:
        return False


_POSITIVE_ACTUATOR_FIELDS = {
    "increment": "counts per metre",
    "offset": "m",
    "pivot_radius": "m",
}
"""Fields of :class:`LinearActuators` that must be finite and positive (their unit):
the actuator law divides by each."""


def known_values(x: typing.Any) -> np.ndarray | None:
    """``x`` as a float NumPy array where its values are known, None under a trace
    (jit, vmap: a tracer) or for a shape-only stand-in."""
    if isinstance(x, (jax.core.Tracer, jax.ShapeDtypeStruct)):  # pyright: ignore[reportAttributeAccessIssue]
        return None
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        return None


@typing.final
class LinearActuators(eqx.Module):
    """The two linear actuators of a heliostat; every field has shape ``(2,)``
    (axis 1, axis 2) or ``(..., 2)`` when batched over heliostats.

    Attributes:
        increment: counts per metre of stroke.
        initial_stroke_length: stroke at count 0, m.
        offset: fixed side of the actuator triangle, m.
        pivot_radius: rotating side of the actuator triangle, m.
        initial_angle: joint angle at count 0, rad.
        sign: +1 where ``clockwise_axis_movement == 0`` (the joint angle grows
            with the counts), -1 where it is 1.
        min_counts: ``min_increment``, counts.
        max_counts: ``max_increment``, counts.
    """

    increment: Float[Array, "*b 2"]
    initial_stroke_length: Float[Array, "*b 2"]
    offset: Float[Array, "*b 2"]
    pivot_radius: Float[Array, "*b 2"]
    initial_angle: Float[Array, "*b 2"]
    sign: Float[Array, "*b 2"]
    min_counts: Float[Array, "*b 2"]
    max_counts: Float[Array, "*b 2"]

    def __check_init__(self):
        shapes = {jnp.shape(getattr(self, f)) for f in self.__dataclass_fields__}
        if len(shapes) != 1 or next(iter(shapes))[-1:] != (2,):
            raise ValueError(f"LinearActuators fields must share a shape (..., 2), got {shapes}")
        # values are checked where they are known (not under jit / vmap, where the
        # fields are tracers): an increment of 0 had divided the counts by zero, a sign of
        # 0 had made a joint that never turns, a NaN angle or count range NaN poses
        for name in self.__dataclass_fields__:
            values = known_values(getattr(self, name))
            if values is None:
                continue
            if name in _POSITIVE_ACTUATOR_FIELDS:
                bad = ~(np.isfinite(values) & (values > 0.0))
                rule = f"finite and > 0 ({_POSITIVE_ACTUATOR_FIELDS[name]})"
            elif name == "sign":
                bad = ~np.isin(values, (-1.0, 1.0))
                rule = "+1 or -1 (clockwise_axis_movement 0 or 1)"
            else:
                bad = ~np.isfinite(values)
                rule = "finite"
            if bad.any():
                at = tuple(int(i) for i in np.argwhere(bad)[0])
                where = f"axis {at[-1] + 1}" + (f" of heliostat {at[0]}" if values.ndim == 2 else "")
                where = where if values.ndim <= 2 else f"index {at}"
                raise ValueError(f"LinearActuators: {name} must be {rule}, got {float(values[at])} at {where}")

    def counts_to_angles(
        self, counts: Float[ArrayLike, "*b 2"], stroke_scale: Float[ArrayLike, "*b 2"] | float = 1.0
    ) -> Float[Array, "*b 2"]:
        """Joint angles (rad) of motor counts by the law of cosines; with
        ``stroke_scale``, of an actuator whose whole stroke (its extended length,
        ``counts / increment + initial_stroke_length``) is that factor longer, e.g. a
        spindle expanded by heat (the angle at count 0 stays ``initial_angle`` only
        for a factor of 1)."""
        counts = jnp.asarray(counts)
        stroke = (counts / self.increment + self.initial_stroke_length) * stroke_scale
        psi = _actuator_psi(stroke, self.offset, self.pivot_radius)
        psi0 = _actuator_psi(self.initial_stroke_length, self.offset, self.pivot_radius)
        return self.initial_angle + self.sign * (psi - psi0)

    def angles_to_counts(self, angles: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 2"]:
        """Motor counts (float) that produce joint angles ``angles`` (inverse law)."""
        angles = jnp.asarray(angles)
        psi0 = _actuator_psi(self.initial_stroke_length, self.offset, self.pivot_radius)
        psi = psi0 + (angles - self.initial_angle) * self.sign
        stroke = jnp.sqrt(self.offset**2 + self.pivot_radius**2 - 2.0 * self.offset * self.pivot_radius * jnp.cos(psi))
        return (stroke - self.initial_stroke_length) * self.increment

    def linearised(self, n: int = 257) -> tuple[Float[Array, "*b 2"], Float[Array, "*b 2"]]:
        """``(slope, intercept)`` of the least-squares line ``angle = slope * counts +
        intercept`` through the actuator law, sampled at ``n`` uniform counts over
        ``[min_counts, max_counts]`` (rad/count, rad)."""
        lead = (1,) * (jnp.ndim(self.min_counts) - 1)
        t = jnp.linspace(0.0, 1.0, n, dtype=jnp.result_type(self.min_counts)).reshape(lead + (n, 1))
        counts = self.min_counts[..., None, :] + t * (self.max_counts - self.min_counts)[..., None, :]  # (*b, n, 2)
        batched = jax.tree_util.tree_map(lambda x: x[..., None, :], self)
        angles = batched.counts_to_angles(counts)
        cm = counts.mean(-2, keepdims=True)
        am = angles.mean(-2, keepdims=True)
        slope = ((counts - cm) * (angles - am)).sum(-2) / ((counts - cm) ** 2).sum(-2)
        intercept = am[..., 0, :] - slope * cm[..., 0, :]
        return slope, intercept


@typing.final
class HeliostatGeometry(eqx.Module):
    """What is measured once per heliostat (ENU metres, rad); batched with a
    leading heliostat axis in a fleet.

    Attributes:
        position: ``(3,)`` ``P``, the heliostat's reference point (PAINT ``heliostat_position``).
        joint_translation_1: ``(3,)`` ``V01``.
        joint_translation_2: ``(3,)`` ``V12`` (axis offset between the joints).
        concentrator_translation: ``(3,)`` ``V2M`` (axis 2 to mirror centre).
        actuators: the two :class:`LinearActuators`.
        linear_slope: ``(2,)`` rad/count of the Stone model's nominal linear map.
        linear_intercept: ``(2,)`` rad of the Stone model's nominal linear map.
        ideal_axes: ``(2,)`` bool, axes whose actuator the plant declares *ideal*
            (joint angle linear in the counts, PAINT ``type_axis == "ideal"``).
    """

    position: Float[Array, "*b 3"]
    joint_translation_1: Float[Array, "*b 3"]
    joint_translation_2: Float[Array, "*b 3"]
    concentrator_translation: Float[Array, "*b 3"]
    actuators: LinearActuators
    linear_slope: Float[Array, "*b 2"]
    linear_intercept: Float[Array, "*b 2"]
    ideal_axes: Bool[Array, "*b 2"]

    @classmethod
    def build(
        cls,
        position,
        actuators: LinearActuators,
        joint_translation_1=(0.0, 0.0, 0.0),
        joint_translation_2=(0.0, 0.0, 0.0),
        concentrator_translation=(0.0, 0.0, 0.0),
        ideal_axes=(False, False),
    ) -> HeliostatGeometry:
        """Geometry with the Stone linear map derived from ``actuators``.

        ``ideal_axes``: per axis, whether the plant declares an *ideal* actuator
        (PAINT ``type_axis == "ideal"``: the joint angle is linear in the counts),
        ``(2,)`` or batched like the actuators; the law-of-cosines actuator model
        then uses the linear map on that axis (see :class:`ActuatorModel`).

        A ``position`` of integers is taken as JAX's default float (the translations
        take its dtype: ``(0, 0.175, 0)`` had been truncated to zeros).

        Raises:
            TypeError: ``position`` or a translation that is no array of real numbers
                (text had failed inside JAX), ``ideal_axes`` that are not booleans
                (``("no", "no")`` had been read as two ideal axes, 0.5 as True).
            ValueError: ``position`` is no ``(..., 3)`` array of finite values, or another
                argument's heliostat axes differ from its (each named with its shape)."""
        for name, value in (
            ("position", position),
            ("joint_translation_1", joint_translation_1),
            ("joint_translation_2", joint_translation_2),
            ("concentrator_translation", concentrator_translation),
        ):
            check_numeric(value, f"HeliostatGeometry.build: {name}", "ENU metres (real numbers)", bools=False)
        if not isinstance(ideal_axes, jax.core.Tracer):  # pyright: ignore[reportAttributeAccessIssue]
            flags = np.asarray(ideal_axes)
            if flags.dtype.kind not in "biu" or not np.isin(flags, (0, 1)).all():
                raise TypeError(f"HeliostatGeometry.build: ideal_axes must be booleans, got {ideal_axes!r}"[:200])
        known = known_values(position)
        if known is not None and not np.isfinite(known).all():  # a NaN had made every pose NaN
            raise ValueError(f"HeliostatGeometry.build: position must be finite ENU metres, got {position!r}"[:200])
        pos = jnp.asarray(position)
        batch = tuple(pos.shape[:-1])
        if pos.shape[-1:] != (3,):
            raise ValueError(f"HeliostatGeometry.build: position has shape {pos.shape}; expected (..., 3)")
        shapes = {
            "actuators": (tuple(jnp.shape(actuators.increment)), batch + (2,)),
            "joint_translation_1": (tuple(np.shape(joint_translation_1)), batch + (3,)),
            "joint_translation_2": (tuple(np.shape(joint_translation_2)), batch + (3,)),
            "concentrator_translation": (tuple(np.shape(concentrator_translation)), batch + (3,)),
            "ideal_axes": (tuple(np.shape(ideal_axes)), batch + (2,)),
        }
        for name, (got, want) in shapes.items():
            exact = name == "actuators"  # the others may be one heliostat's, broadcast
            if got != want and (exact or not _broadcasts_to(got, want)):
                raise ValueError(
                    f"HeliostatGeometry.build: {name} has shape {got}, but position {pos.shape} holds "
                    f"{'one heliostat' if not batch else f'heliostats {batch}'}: expected {want}"
                    + ("" if exact else f" or {want[-1:]} (one for all)")
                )
        slope, intercept = actuators.linearised()
        if not jnp.issubdtype(pos.dtype, jnp.inexact):
            pos = pos.astype(jnp.result_type(float))
        return cls(
            position=pos,
            joint_translation_1=jnp.broadcast_to(jnp.asarray(joint_translation_1, pos.dtype), pos.shape),
            joint_translation_2=jnp.broadcast_to(jnp.asarray(joint_translation_2, pos.dtype), pos.shape),
            concentrator_translation=jnp.broadcast_to(jnp.asarray(concentrator_translation, pos.dtype), pos.shape),
            actuators=actuators,
            linear_slope=slope,
            linear_intercept=intercept,
            ideal_axes=jnp.broadcast_to(jnp.asarray(ideal_axes, bool), jnp.shape(slope)),
        )


# --------------------------------------------------------------------------------------
# What a record carries besides the counts
# --------------------------------------------------------------------------------------


@typing.final
class RecordContext(eqx.Module):
    """Everything a record carries besides its motor counts (one record; batched
    with leading axes in fleets). Missing values are NaN.

    Attributes:
        sun: ``(3,)`` unit ENU vector to the sun.
        unix_time: s since 1970-01-01 UTC (NaN if unknown).
        temperature: ambient temperature, deg C.
        wind_speed: m/s.
        wind_direction: rad, direction the wind comes from, clockwise from north.
        approach: ``(2,)`` sign (+1/-1, 0 unknown) of the last motion of each axis
            before the record (for backlash / hysteresis).
        target: int, the calibration target the spot was measured on: an index into
            the fleet's ``target_names`` (``-1`` unknown). In a
            :class:`~heliojax.Fleet` this *is* ``Fleet.target_index`` (one array).
    """

    sun: Float[Array, "*b 3"]
    unix_time: Float[Array, "*b"]
    temperature: Float[Array, "*b"]
    wind_speed: Float[Array, "*b"]
    wind_direction: Float[Array, "*b"]
    approach: Float[Array, "*b 2"]
    target: Int[Array, "*b"]

    @classmethod
    def from_sun(cls, sun, unix_time=None, target=None) -> RecordContext:
        """A context with only the sun direction (and optionally the time and the
        target index; default ``-1``, unknown) known."""
        sun = jnp.asarray(sun)
        nan = jnp.full(sun.shape[:-1], jnp.nan, sun.dtype)
        t = nan if unix_time is None else jnp.broadcast_to(jnp.asarray(unix_time, sun.dtype), nan.shape)
        k = -1 if target is None else target
        return cls(
            sun=sun,
            unix_time=t,
            temperature=nan,
            wind_speed=nan,
            wind_direction=nan,
            approach=jnp.zeros(sun.shape[:-1] + (2,), sun.dtype),
            target=jnp.broadcast_to(jnp.asarray(k, jnp.int32), nan.shape),
        )


@typing.final
class Pose(eqx.Module):
    """An aligned heliostat.

    Attributes:
        normal: ``(3,)`` unit mirror normal, ENU.
        centre: ``(3,)`` mirror centre, ENU m.
        rotation: ``(3, 3)`` surface frame (normal +z) -> ENU; ``rotation[:, 2] == normal``.
    """

    normal: Float[Array, "*b 3"]
    centre: Float[Array, "*b 3"]
    rotation: Float[Array, "*b 3 3"]


def _chain_rotations(tilts, angles):
    alpha, beta, gamma, delta = tilts[0], tilts[1], tilts[2], tilts[3]
    r01 = matmul3(rotation_y(alpha), rotation_z(beta))
    r_theta = rotation_x(angles[0] - _HALF_PI)
    r12 = rotation_y(gamma)
    r_tau = rotation_z(angles[1])
    r2m = rotation_x(delta)
    return r01, r_theta, r12, r_tau, r2m


def chain_pose(tilts: Float[Array, "4"], angles: Float[Array, "2"], geometry: HeliostatGeometry) -> Pose:
    """The shared rotation chain: tilts ``(alpha, beta, gamma, delta)`` and joint
    angles ``(theta, tau)`` (rad) -> :class:`Pose`."""
    r01, r_theta, r12, r_tau, r2m = _chain_rotations(tilts, angles)
    outer = matmul3(r01, r_theta)
    inner = matmul3(r12, r_tau)
    body = matmul3(matmul3(outer, inner), r2m)
    n_ba = jnp.asarray(N_BA, dtype=body.dtype)
    normal = matvec3(body, n_ba)
    centre = (
        geometry.position
        + geometry.joint_translation_1
        + matvec3(outer, geometry.joint_translation_2 + matvec3(inner, geometry.concentrator_translation))
    )
    rotation = matmul3(body, rotation_x(jnp.asarray(_HALF_PI, body.dtype)))
    return Pose(normal=normal, centre=centre, rotation=rotation)


def solve_chain_angles(tilts, normal, tau_reference):
    """Joint angles ``(theta, tau)`` for which the chain's normal equals ``normal``.

    Closed form: the x-component in axis 1's frame fixes ``tau`` (two roots; the
    one nearest ``tau_reference`` is taken), then ``theta`` follows from the y-z
    components.
    """
    alpha, beta, gamma, delta = tilts[0], tilts[1], tilts[2], tilts[3]
    r01 = matmul3(rotation_y(alpha), rotation_z(beta))
    m = matvec3(r01.T, normal)
    v = matvec3(rotation_x(delta), jnp.asarray(N_BA, dtype=normal.dtype))
    a = jnp.cos(gamma) * v[0]
    b = -jnp.cos(gamma) * v[1]
    c = m[0] - jnp.sin(gamma) * v[2]
    rho = jnp.hypot(a, b)
    phase = jnp.arctan2(b, a)
    half = jnp.arccos(jnp.clip(c / rho, -1.0, 1.0))
    tau_candidates = jnp.stack([phase - half, phase + half])
    wrapped = jnp.mod(tau_candidates - tau_reference + jnp.pi, 2 * jnp.pi) - jnp.pi + tau_reference
    tau = wrapped[jnp.argmin(jnp.abs(wrapped - tau_reference))]
    u = matvec3(rotation_y(gamma), matvec3(rotation_z(tau), v))
    phi = jnp.arctan2(m[2], m[1]) - jnp.arctan2(u[2], u[1])
    phi = jnp.mod(phi + jnp.pi, 2 * jnp.pi) - jnp.pi
    theta = phi + _HALF_PI
    return jnp.stack([theta, tau])


__all__ = [
    "N_BA",
    "HeliostatGeometry",
    "LinearActuators",
    "Pose",
    "RecordContext",
    "chain_pose",
    "known_values",
    "solve_chain_angles",
]
