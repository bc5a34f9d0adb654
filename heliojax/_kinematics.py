"""Heliostat kinematics: the Stone error model and the Jülich linear-actuator model.

Both models share one rotation chain (Stone 1986; Pargmann et al.) and differ
only in how motor counts become joint angles.

The chain itself, its frames and signs, are in :mod:`heliojax._heliostat`.

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
from jaxtyping import Array, ArrayLike, Float

from ._beam import beam_error_components, beam_pointing_error
from ._geometry import bisector_normal, normalize
from ._heliostat import HeliostatGeometry, LinearActuators, Pose, RecordContext, chain_pose, solve_chain_angles
from ._parameters import check_fields, is_batched, parameter, parameter_leaves

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

    A model's own parameter fields are checked where their values are concrete
    (:func:`heliojax._parameters.check_fields`): real, finite, of their declared shape.
    """

    def __check_init__(self):
        check_fields(self)

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


@eqx.filter_jit
def inverse_normal(
    model: AbstractKinematicModel, geometry: HeliostatGeometry, normal: Float[ArrayLike, "3"]
) -> Float[Array, "2"]:
    """Motor counts (float) that align the mirror normal with ``normal`` (unit, ENU).

    Raises:
        ValueError: ``normal`` not of shape ``(3,)`` (vmap for many)."""
    normal = jnp.asarray(normal)
    if normal.shape != (3,):
        raise ValueError(
            f"inverse_normal: normal has shape {normal.shape}; expected (3,), one ENU vector (vmap for many)"
        )
    normal = normalize(normal)
    angles = solve_chain_angles(model.tilts(), normal, jnp.zeros((), normal.dtype))
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
        sun: ``(3,)`` vector towards the sun; only its direction counts (a vector
            of any non-zero length is normalised: the bisector of a non-unit sun
            and the unit aim direction is not the mirror normal).
        iterations: fixed-point iterations (static).

    Returns:
        ``(2,)`` counts; NaN for a zero or non-finite ``sun`` (no direction to
        reflect: a zero vector had given plausible finite counts). No error is
        raised for values, so that the function stays jittable and vmappable.

    Raises:
        ValueError: ``aim_point`` or ``sun`` not of shape ``(3,)``.
    """
    aim = jnp.asarray(aim_point)
    raw_sun = jnp.asarray(sun)
    for name, value in (("aim_point", aim), ("sun", raw_sun)):  # shapes are static, also under jit and vmap
        if value.shape != (3,):
            raise ValueError(
                f"inverse_aim: {name} must have shape (3,) (one ENU vector; vmap for many), not {value.shape}"
            )
    degenerate = ~(jnp.all(jnp.isfinite(raw_sun)) & (jnp.sum(raw_sun * raw_sun) > 0.0))
    sun = normalize(jnp.where(degenerate, jnp.array([0.0, 0.0, 1.0], raw_sun.dtype), raw_sun))
    centre0 = geometry.position + geometry.joint_translation_1

    def step(_, centre):
        normal = bisector_normal(sun, normalize(aim - centre))
        counts = inverse_normal(model, geometry, normal)
        return model.pose(geometry, counts).centre

    centre = jax.lax.fori_loop(0, iterations - 1, step, centre0)
    counts = inverse_normal(model, geometry, bisector_normal(sun, normalize(aim - centre)))
    return jnp.where(degenerate, jnp.nan, counts)


@typing.final
class StoneModel(AbstractKinematicModel):
    """The eight Stone error parameters (rad, gear ratios dimensionless).

    Nominal (uncalibrated) values: all angles 0, ``gr1 = gr2 = 1``. The gear ratios
    divide the motor angles: a (concrete) one must be > 0.
    """

    alpha: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    beta: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    gamma: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    delta: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    theta_k: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-2)
    tau_k: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-2)
    gr1: Float[Array, "*h"] = parameter(unit="1", scale=1e-2, typical=1e-2, nominal=1.0, above=0.0)
    gr2: Float[Array, "*h"] = parameter(unit="1", scale=1e-2, typical=1e-2, nominal=1.0, above=0.0)

    JOINT_LAW: typing.ClassVar[str] = "linear"

    def label(self) -> str:
        return "stone8"

    @classmethod
    def nominal(cls, dtype=None) -> StoneModel:
        dtype = _float_dtype(dtype)  # NumPy arrays put on the device: no eager XLA ops
        z = jax.device_put(np.zeros((), dtype))
        o = jax.device_put(np.ones((), dtype))
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
            the effective increment is ``increment * (1 + increment_scale)``, so a
            (concrete) one must be > -1.
        stroke_offset: ``(2,)`` added to ``initial_stroke_length``, m (weakly
            identifiable: nearly collinear with the two above over a calibration's
            range; fit with a prior).
    """

    alpha: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    beta: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    gamma: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    delta: Float[Array, "*h"] = parameter(unit="rad", scale=1e-2, typical=1e-3)
    angle_offset: Float[Array, "*h 2"] = parameter(unit="rad", scale=1e-2, typical=1e-2, shape=(2,))
    increment_scale: Float[Array, "*h 2"] = parameter(unit="1", scale=1e-2, typical=1e-2, shape=(2,), above=-1.0)
    stroke_offset: Float[Array, "*h 2"] = parameter(unit="m", scale=1e-2, typical=1e-3, shape=(2,))

    JOINT_LAW: typing.ClassVar[str] = "actuator"

    def label(self) -> str:
        return "actuator"

    def fixed_parameter_fields(self) -> tuple[str, ...]:
        """Not fitted by default: the stroke offsets (nearly collinear with the angle
        offsets and increment scales over a calibration's range; free them with a prior)."""
        return ("stroke_offset",)

    @classmethod
    def nominal(cls, dtype=None) -> ActuatorModel:
        dtype = _float_dtype(dtype)  # NumPy arrays put on the device: no eager XLA ops
        z = jax.device_put(np.zeros((), dtype))
        z2 = jax.device_put(np.zeros((2,), dtype))
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


def _float_dtype(dtype: typing.Any) -> typing.Any:
    """``jnp.zeros((), dtype).dtype``: the default float type for None."""
    return jax.dtypes.canonicalize_dtype(np.float64 if dtype is None else dtype)


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

    Raises:
        ValueError: ``counts`` not of shape ``(2,)``, or ``geometry`` or ``model``
            batched over heliostats (checked under ``jit`` and ``vmap`` too: shapes are
            static). Counts of shape ``(1,)`` had been used for both axes.
    """
    counts = jnp.asarray(counts)
    if counts.shape != (2,):
        raise ValueError(
            f"forward: counts has shape {counts.shape}; expected (2,), the motor counts (axis 1, axis 2) of one "
            "record (jax.vmap over records and heliostats)"
        )
    _check_one_heliostat("forward", model, geometry)
    return model.pose(geometry, counts, context)


def _check_one_heliostat(function: str, model: AbstractKinematicModel, geometry: HeliostatGeometry) -> None:
    """ValueError where ``geometry`` or ``model`` carries a heliostat axis: a function of
    one heliostat had failed deep inside the rotation chain (a ``dot_general`` shape
    error) or broadcast the batch against the record."""
    position = jnp.shape(geometry.position)
    if position != (3,):
        raise ValueError(
            f"{function}: geometry.position has shape {position}; expected (3,), the geometry of one heliostat "
            "(jax.vmap over a fleet's heliostats, or take one with fleet.heliostat(i))"
        )
    if parameter_leaves(model) and is_batched(model):  # a model of one's own may have no parameter
        raise ValueError(
            f"{function}: model is batched over heliostats; expected the model of one heliostat "
            "(solution.heliostat_model(i), or jax.vmap over the heliostats)"
        )


__all__ = [
    "AbstractKinematicModel",
    "AbstractModelWrapper",
    "ActuatorModel",
    "MODEL_KINDS",
    "StoneModel",
    "forward",
    "inverse_aim",
    "inverse_normal",
    "nominal_model",
]
