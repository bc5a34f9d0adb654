"""Heliostat kinematics: the Stone error model and the Jülich linear-actuator model.

Both models share one rotation chain (Stone 1986; Pargmann et al.) and differ
only in how motor counts become joint angles.

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

Counts to joint angles
----------------------

*Linear actuators* (the real Jülich geometry, per axis ``i``)::

    stroke_i  = counts_i / increment_i + initial_stroke_length_i        [m]
    psi(s)    = arccos((offset^2 + pivot_radius^2 - s^2) / (2 offset pivot_radius))
    angle_i   = initial_angle_i + sign_i * (psi(stroke_i) - psi(initial_stroke_length_i))
    sign_i    = +1 if clockwise_axis_movement == 0 else -1

(``increment`` is counts per metre of stroke.) On the shared records this
law reproduces the measured joint-angle slopes to 0.1-2 % (axis 1) and
< 1 % (axis 2).

*Stone model*: a nominal **linear** counts-to-angle map, the least-squares
straight line through the actuator law over the full count range
``[min_increment, max_increment]`` (the actuator geometry linearised about
mid-stroke), ``theta_M = slope * counts + intercept``. The model angle is
``theta = theta_M / GR1 + theta_k`` (likewise ``tau`` with ``GR2, tau_k``), so
the gear ratios and offsets absorb the linearisation's scale and zero. The
residual curvature of the actuator law (up to ~1.5 deg) is *not* representable
by the Stone model; the discovery workflow names it.
"""

from __future__ import annotations

import abc
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._geometry import (
    angle_between,
    bisector_normal,
    intersect_plane,
    normalize,
    reflect,
    rotation_x,
    rotation_y,
    rotation_z,
)
from ._parameters import parameter

_HALF_PI = np.pi / 2.0
N_BA = (0.0, -1.0, 0.0)
"""Mirror normal in the body frame at the reference pose (PAINT ``initial_orientation``)."""


# --------------------------------------------------------------------------------------
# Geometry measured once per heliostat
# --------------------------------------------------------------------------------------


def _actuator_psi(stroke, offset, pivot_radius):
    cos_psi = (offset**2 + pivot_radius**2 - stroke**2) / (2.0 * offset * pivot_radius)
    return jnp.arccos(jnp.clip(cos_psi, -1.0, 1.0))


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

    def counts_to_angles(self, counts: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 2"]:
        """Joint angles (rad) of motor counts by the law of cosines."""
        counts = jnp.asarray(counts)
        stroke = counts / self.increment + self.initial_stroke_length
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
        t = jnp.broadcast_to(
            jnp.linspace(0.0, 1.0, n, dtype=jnp.result_type(self.min_counts)), (*jnp.shape(self.min_counts), n)
        )
        counts = self.min_counts[..., None] + t * (self.max_counts - self.min_counts)[..., None]
        batched = jax.tree_util.tree_map(lambda x: x[..., None], self)
        angles = batched.counts_to_angles(counts)
        cm = counts.mean(-1, keepdims=True)
        am = angles.mean(-1, keepdims=True)
        slope = ((counts - cm) * (angles - am)).sum(-1) / ((counts - cm) ** 2).sum(-1)
        intercept = am[..., 0] - slope * cm[..., 0]
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
        then uses the linear map on that axis (see :class:`ActuatorModel`)."""
        slope, intercept = actuators.linearised()
        pos = jnp.asarray(position)
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
    """

    sun: Float[Array, "*b 3"]
    unix_time: Float[Array, "*b"]
    temperature: Float[Array, "*b"]
    wind_speed: Float[Array, "*b"]
    wind_direction: Float[Array, "*b"]
    approach: Float[Array, "*b 2"]

    @classmethod
    def from_sun(cls, sun, unix_time=None) -> RecordContext:
        """A context with only the sun direction (and optionally the time) known."""
        sun = jnp.asarray(sun)
        nan = jnp.full(sun.shape[:-1], jnp.nan, sun.dtype)
        t = nan if unix_time is None else jnp.broadcast_to(jnp.asarray(unix_time, sun.dtype), nan.shape)
        return cls(
            sun=sun,
            unix_time=t,
            temperature=nan,
            wind_speed=nan,
            wind_direction=nan,
            approach=jnp.zeros(sun.shape[:-1] + (2,), sun.dtype),
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


# --------------------------------------------------------------------------------------
# Models (the fitted parameters)
# --------------------------------------------------------------------------------------


class AbstractKinematicModel(eqx.Module):
    """A kinematic model: fitted parameters (fields declared with
    :func:`heliojax.parameter`) and the map from motor counts to a pose.

    Base models (:class:`StoneModel`, :class:`ActuatorModel`) provide the four
    chain tilts and the counts <-> joint-angle maps. Wrappers (effects,
    :class:`heliojax.neural.NeuralCorrection`) hold an inner model and override the
    record-level hooks below, delegating to the inner model first, so wrappers
    compose in any order without losing each other's behaviour:

    * :meth:`adjusted_geometry` - the surveyed geometry the model believes in;
    * :meth:`record_angles` - joint angles of a record (may use its context);
    * :meth:`sun` - the sun direction the model believes in;
    * :meth:`spot` - the measured focal spot as the model corrects it.

    :meth:`pose` and the beam error are defined once, from these hooks.
    """

    @abc.abstractmethod
    def tilts(self) -> Float[Array, "4"]:
        """``(alpha, beta, gamma, delta)`` in rad."""

    @abc.abstractmethod
    def joint_angles(self, geometry: HeliostatGeometry, counts: Float[Array, "2"]) -> Float[Array, "2"]:
        """Joint angles ``(theta, tau)`` in rad of motor counts (no record context)."""

    @abc.abstractmethod
    def counts(self, geometry: HeliostatGeometry, angles: Float[Array, "2"]) -> Float[Array, "2"]:
        """Inverse of :meth:`joint_angles`: motor counts (float) of joint angles."""

    def label(self) -> str:
        """Short name of the model for reports (``"stone8"``, ``"actuator+backlash"``)."""
        return type(self).__name__

    def adjusted_geometry(self, geometry: HeliostatGeometry) -> HeliostatGeometry:
        """The geometry the model believes in (survey effects move it); default: as given."""
        return geometry

    def record_angles(
        self, geometry: HeliostatGeometry, counts: Float[Array, "2"], context: RecordContext | None
    ) -> Float[Array, "2"]:
        """Joint angles (rad) of one record; effects add context-dependent terms.
        Default: :meth:`joint_angles`."""
        del context
        return self.joint_angles(geometry, counts)

    def pose(
        self, geometry: HeliostatGeometry, counts: Float[Array, "2"], context: RecordContext | None = None
    ) -> Pose:
        """Aligned mirror of one record (see the module docstring for the chain)."""
        g = self.adjusted_geometry(geometry)
        return chain_pose(self.tilts(), self.record_angles(g, jnp.asarray(counts), context), g)

    def sun(self, geometry: HeliostatGeometry, context: RecordContext) -> Float[Array, "3"]:
        """The sun direction the model believes in for a record (effects such as a
        clock error or refraction override it); default: the recorded one."""
        del geometry
        return context.sun

    def spot(self, focal_spot: Float[Array, "3"], context: RecordContext) -> Float[Array, "3"]:
        """The measured focal spot (ENU m) as the model corrects it (target survey
        effects move it); default: as measured."""
        del context
        return jnp.asarray(focal_spot)

    def beam_components(
        self,
        geometry: HeliostatGeometry,
        counts: Float[Array, "2"],
        context: RecordContext,
        focal_spot: Float[Array, "3"],
    ) -> Float[Array, "2"]:
        """Tangent-plane beam error components (rad) of one record under this model:
        the calibration residual."""
        return beam_error_components(
            self.pose(geometry, counts, context), self.sun(geometry, context), self.spot(focal_spot, context)
        )

    def beam_error(
        self,
        geometry: HeliostatGeometry,
        counts: Float[Array, "2"],
        context: RecordContext,
        focal_spot: Float[Array, "3"],
    ) -> Float[Array, ""]:
        """Beam pointing error (rad) of one record under this model."""
        return beam_pointing_error(
            self.pose(geometry, counts, context), self.sun(geometry, context), self.spot(focal_spot, context)
        )


class AbstractModelWrapper(AbstractKinematicModel):
    """A model that wraps an inner model (``inner``) and delegates every hook to
    it; subclasses add their own behaviour on top (effects, neural correction)."""

    inner: eqx.AbstractVar[AbstractKinematicModel]

    @property
    def base(self) -> AbstractKinematicModel:
        """The innermost (base) model."""
        m = self.inner
        while isinstance(m, AbstractModelWrapper):
            m = m.inner
        return m

    def tilts(self):
        return self.inner.tilts()

    def joint_angles(self, geometry, counts):
        return self.inner.joint_angles(geometry, counts)

    def counts(self, geometry, angles):
        return self.inner.counts(geometry, angles)

    def adjusted_geometry(self, geometry):
        return self.inner.adjusted_geometry(geometry)

    def record_angles(self, geometry, counts, context):
        return self.inner.record_angles(geometry, counts, context)

    def sun(self, geometry, context):
        return self.inner.sun(geometry, context)

    def spot(self, focal_spot, context):
        return self.inner.spot(focal_spot, context)


def _chain_rotations(tilts, angles):
    alpha, beta, gamma, delta = tilts[0], tilts[1], tilts[2], tilts[3]
    r01 = rotation_y(alpha) @ rotation_z(beta)
    r_theta = rotation_x(angles[0] - _HALF_PI)
    r12 = rotation_y(gamma)
    r_tau = rotation_z(angles[1])
    r2m = rotation_x(delta)
    return r01, r_theta, r12, r_tau, r2m


def chain_pose(tilts: Float[Array, "4"], angles: Float[Array, "2"], geometry: HeliostatGeometry) -> Pose:
    """The shared rotation chain: tilts ``(alpha, beta, gamma, delta)`` and joint
    angles ``(theta, tau)`` (rad) -> :class:`Pose`."""
    r01, r_theta, r12, r_tau, r2m = _chain_rotations(tilts, angles)
    outer = r01 @ r_theta
    body = outer @ r12 @ r_tau @ r2m
    n_ba = jnp.asarray(N_BA, dtype=body.dtype)
    normal = body @ n_ba
    centre = (
        geometry.position
        + geometry.joint_translation_1
        + outer @ (geometry.joint_translation_2 + r12 @ r_tau @ geometry.concentrator_translation)
    )
    rotation = body @ rotation_x(jnp.asarray(_HALF_PI, body.dtype))
    return Pose(normal=normal, centre=centre, rotation=rotation)


def _solve_chain_angles(tilts, normal, tau_reference):
    """Joint angles ``(theta, tau)`` for which the chain's normal equals ``normal``.

    Closed form: the x-component in axis 1's frame fixes ``tau`` (two roots; the
    one nearest ``tau_reference`` is taken), then ``theta`` follows from the y-z
    components.
    """
    alpha, beta, gamma, delta = tilts[0], tilts[1], tilts[2], tilts[3]
    r01 = rotation_y(alpha) @ rotation_z(beta)
    m = r01.T @ normal
    v = rotation_x(delta) @ jnp.asarray(N_BA, dtype=normal.dtype)
    a = jnp.cos(gamma) * v[0]
    b = -jnp.cos(gamma) * v[1]
    c = m[0] - jnp.sin(gamma) * v[2]
    rho = jnp.hypot(a, b)
    phase = jnp.arctan2(b, a)
    half = jnp.arccos(jnp.clip(c / rho, -1.0, 1.0))
    tau_candidates = jnp.stack([phase - half, phase + half])
    wrapped = jnp.mod(tau_candidates - tau_reference + jnp.pi, 2 * jnp.pi) - jnp.pi + tau_reference
    tau = wrapped[jnp.argmin(jnp.abs(wrapped - tau_reference))]
    u = rotation_y(gamma) @ rotation_z(tau) @ v
    phi = jnp.arctan2(m[2], m[1]) - jnp.arctan2(u[2], u[1])
    phi = jnp.mod(phi + jnp.pi, 2 * jnp.pi) - jnp.pi
    theta = phi + _HALF_PI
    return jnp.stack([theta, tau])


@eqx.filter_jit
def inverse_normal(
    model: AbstractKinematicModel, geometry: HeliostatGeometry, normal: Float[ArrayLike, "3"]
) -> Float[Array, "2"]:
    """Motor counts (float) that align the mirror normal with ``normal`` (unit, ENU)."""
    normal = normalize(jnp.asarray(normal))
    angles = _solve_chain_angles(model.tilts(), normal, jnp.zeros((), normal.dtype))
    return model.counts(geometry, angles)


@eqx.filter_jit
def inverse_aim(
    model: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    aim_point: Float[ArrayLike, "3"],
    sun: Float[ArrayLike, "3"],
    iterations: int = 8,
) -> Float[Array, "2"]:
    """Motor counts (float) that reflect the sun onto ``aim_point`` (ENU m).

    The mirror centre moves with the pose (axis offsets), so the bisector normal
    and the centre are iterated to a fixed point; the offset/distance ratio
    (~1e-3) makes each iteration gain ~3 digits.

    Args:
        model: fitted parameters.
        geometry: the heliostat.
        aim_point: ``(3,)`` ENU m.
        sun: ``(3,)`` unit vector to the sun.
        iterations: fixed-point iterations (static).
    """
    aim = jnp.asarray(aim_point)
    sun = jnp.asarray(sun)
    centre0 = geometry.position + geometry.joint_translation_1

    def step(_, centre):
        normal = bisector_normal(sun, normalize(aim - centre))
        counts = inverse_normal(model, geometry, normal)
        return model.pose(geometry, counts).centre

    centre = jax.lax.fori_loop(0, iterations - 1, step, centre0)
    return inverse_normal(model, geometry, bisector_normal(sun, normalize(aim - centre)))


@typing.final
class StoneModel(AbstractKinematicModel):
    """The eight Stone error parameters (rad, gear ratios dimensionless).

    Nominal (uncalibrated) values: all angles 0, ``gr1 = gr2 = 1``.
    """

    alpha: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    beta: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    gamma: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    delta: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    theta_k: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-2)
    tau_k: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-2)
    gr1: Float[Array, ""] = parameter(unit="1", scale=1e-2, typical=1e-2, nominal=1.0)
    gr2: Float[Array, ""] = parameter(unit="1", scale=1e-2, typical=1e-2, nominal=1.0)

    JOINT_LAW: typing.ClassVar[str] = "linear"

    def label(self) -> str:
        return "stone8"

    @classmethod
    def nominal(cls, dtype=None) -> StoneModel:
        z = jnp.zeros((), dtype)
        o = jnp.ones((), dtype)
        return cls(alpha=z, beta=z, gamma=z, delta=z, theta_k=z, tau_k=z, gr1=o, gr2=o)

    def tilts(self):
        return jnp.stack([self.alpha, self.beta, self.gamma, self.delta])

    def joint_angles(self, geometry, counts):
        motor_angles = geometry.linear_slope * counts + geometry.linear_intercept
        gr = jnp.stack([self.gr1, self.gr2])
        offsets = jnp.stack([self.theta_k, self.tau_k])
        return motor_angles / gr + offsets

    def counts(self, geometry, angles):
        gr = jnp.stack([self.gr1, self.gr2])
        offsets = jnp.stack([self.theta_k, self.tau_k])
        motor_angles = (angles - offsets) * gr
        return (motor_angles - geometry.linear_intercept) / geometry.linear_slope


@typing.final
class ActuatorModel(AbstractKinematicModel):
    """The linear-actuator model's corrections to the nominal geometry.

    Counts become joint angles by the law of cosines of each linear actuator, or,
    on axes whose actuator the plant declares *ideal*
    (``geometry.ideal_axes``), by the linear map ``intercept + angle_offset +
    slope * counts / (1 + increment_scale)`` (the Stone model's map with the same
    two corrections as offset and scale), so fleets that mix both kinds share one
    model and one compiled program.

    Attributes (nominal value 0 for all, so the nominal model is PAINT's geometry):
        alpha, beta, gamma, delta: chain tilts, rad (as in the Stone model).
        angle_offset: ``(2,)`` added to each axis's ``initial_angle``, rad.
        increment_scale: ``(2,)`` relative error of ``increment`` (counts per metre);
            the effective increment is ``increment * (1 + increment_scale)``.
        stroke_offset: ``(2,)`` added to ``initial_stroke_length``, m (weakly
            identifiable: nearly collinear with the two above over a calibration's
            range; fit with a prior).
    """

    alpha: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    beta: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    gamma: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    delta: Float[Array, ""] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    angle_offset: Float[Array, "2"] = parameter(unit="rad", scale=1e-2, typical=1e-2, shape=(2,))
    increment_scale: Float[Array, "2"] = parameter(unit="1", scale=1e-2, typical=1e-2, shape=(2,))
    stroke_offset: Float[Array, "2"] = parameter(unit="m", scale=1e-2, typical=1e-3, shape=(2,))

    JOINT_LAW: typing.ClassVar[str] = "actuator"

    def label(self) -> str:
        return "actuator"

    def fixed_parameter_fields(self) -> tuple[str, ...]:
        """Not fitted by default: the stroke offsets (nearly collinear with the angle
        offsets and increment scales over a calibration's range; free them with a prior)."""
        return ("stroke_offset",)

    @classmethod
    def nominal(cls, dtype=None) -> ActuatorModel:
        z = jnp.zeros((), dtype)
        z2 = jnp.zeros((2,), dtype)
        return cls(alpha=z, beta=z, gamma=z, delta=z, angle_offset=z2, increment_scale=z2, stroke_offset=z2)

    def tilts(self):
        return jnp.stack([self.alpha, self.beta, self.gamma, self.delta])

    def effective_actuators(self, geometry: HeliostatGeometry) -> LinearActuators:
        a = geometry.actuators
        return eqx.tree_at(
            lambda x: (x.increment, x.initial_stroke_length, x.initial_angle),
            a,
            (
                a.increment * (1.0 + self.increment_scale),
                a.initial_stroke_length + self.stroke_offset,
                a.initial_angle + self.angle_offset,
            ),
        )

    def joint_angles(self, geometry, counts):
        counts = jnp.asarray(counts)
        law = self.effective_actuators(geometry).counts_to_angles(counts)
        line = (
            geometry.linear_intercept
            + self.angle_offset
            + geometry.linear_slope * counts / (1.0 + self.increment_scale)
        )
        return jnp.where(geometry.ideal_axes, line, law)

    def counts(self, geometry, angles):
        angles = jnp.asarray(angles)
        law = self.effective_actuators(geometry).angles_to_counts(angles)
        line = (
            (angles - geometry.linear_intercept - self.angle_offset)
            * (1.0 + self.increment_scale)
            / geometry.linear_slope
        )
        return jnp.where(geometry.ideal_axes, line, law)


MODEL_KINDS = ("auto", "stone8", "actuator")
"""Names of the base models (configs and the command line name them so). ``"auto"``
is the actuator model, which follows each heliostat's declared actuator kind
(law of cosines for linear actuators, a linear map for ideal ones)."""


def nominal_model(kind: str, dtype: typing.Any = None) -> AbstractKinematicModel:
    """The nominal (uncalibrated) base model called ``kind`` (:data:`MODEL_KINDS`)."""
    if kind == "stone8":
        return StoneModel.nominal(dtype)
    if kind in ("actuator", "auto"):
        return ActuatorModel.nominal(dtype)
    raise ValueError(f"unknown model {kind!r}; expected one of {MODEL_KINDS}")


def forward(
    model: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    counts: Float[ArrayLike, "2"],
    context: RecordContext | None = None,
) -> Pose:
    """Motor counts -> aligned mirror (normal, centre, rotation) of one record.

    The one pure function that calibration, effects, the simulator and the ray
    tracer build on. vmap it over records and heliostats.

    Args:
        model: fitted parameters (:class:`StoneModel`, :class:`ActuatorModel` or an
            effect-wrapped model).
        geometry: the heliostat.
        counts: ``(2,)`` motor counts (axis 1, axis 2).
        context: the record's sun, time and weather (used by effects).
    """
    return model.pose(geometry, jnp.asarray(counts), context)


# --------------------------------------------------------------------------------------
# Measured quantities and the error metric
# --------------------------------------------------------------------------------------


def measured_normal(
    centre: Float[ArrayLike, "3"], sun: Float[ArrayLike, "3"], focal_spot: Float[ArrayLike, "3"]
) -> Float[Array, "3"]:
    """Normal implied by a record: bisector of the sun direction and the unit vector
    from the mirror centre to the measured focal spot (all ENU)."""
    return bisector_normal(sun, normalize(jnp.asarray(focal_spot) - jnp.asarray(centre)))


def reflected_ray(pose: Pose, sun: Float[ArrayLike, "3"]) -> Float[Array, "3"]:
    """Direction of the central ray reflected at ``pose`` for sunlight from ``sun``."""
    return reflect(-jnp.asarray(sun), pose.normal)


def _tangent_basis(r):
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
    e1, e2 = _tangent_basis(r)
    return jnp.stack([d @ e1, d @ e2])


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
    "AbstractKinematicModel",
    "AbstractModelWrapper",
    "ActuatorModel",
    "HeliostatGeometry",
    "LinearActuators",
    "Pose",
    "RecordContext",
    "StoneModel",
    "beam_error_components",
    "beam_pointing_error",
    "chain_pose",
    "forward",
    "MODEL_KINDS",
    "inverse_aim",
    "nominal_model",
    "inverse_normal",
    "measured_normal",
    "reflected_ray",
    "target_miss_distance",
]
