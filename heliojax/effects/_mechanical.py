"""Mechanical effects: actuator geometry, backlash, gravity sag, encoder wobble.

All four correct the joint angles ``(theta, tau)`` (rad) that the base model
computes from the motor counts (axis 1 = elevation-like tilt ``theta``, axis 2 =
azimuth-like turn ``tau``; see :mod:`heliojax._kinematics`).
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._parameters import parameter
from ._base import AbstractEffect, joint_law, rising_direction, zeros


@typing.final
class ActuatorGeometry(AbstractEffect):
    """Linear-actuator geometry the base model gets wrong.

    Physical meaning: a linear actuator turns a joint through a triangle
    (law of cosines, :class:`~heliojax.LinearActuators`), so the joint angle is
    a *curved* function of the stroke (of the motor counts). Two errors:

    * ``curvature_i`` (dimensionless): the fraction of the nominal actuator
      law's curvature that the model is missing. The Stone model maps counts to
      angles linearly; its gear ratio and offset absorb the law's linear part,
      not its curvature (up to ~25 mrad on the Jülich heliostats). With
      ``curvature = 1`` a Stone model follows the full nominal law.
      Correction: ``curvature_i * (law_i(counts) - line_i(counts))`` with
      ``line`` the least-squares line of the Stone model's nominal map.
    * ``pivot_scale_i`` (dimensionless): relative error of the actuator's pivot
      radius (``pivot_radius * (1 + pivot_scale)``), for a base that already
      follows the law (the actuator model). Correction:
      ``law_i(counts; pivot (1 + s_i)) - law_i(counts; pivot)`` with the nominal
      actuators (the base's small increment / offset corrections change this by
      a second-order amount only, and keeping them out makes the correction
      independent of the base parameters).

    Driving inputs: the motor counts. Residual signature: a smooth, curved
    function of each axis's counts (its linear part is absorbed by the base's
    gear ratio / increment scale and offset).

    The fitted parameters depend on the base's joint law (``law``, static):
    ``curvature_1, curvature_2`` for a linear base (``stone8``),
    ``pivot_scale_1, pivot_scale_2`` for a base that follows the actuator law
    (``actuator``); the other pair stays 0.
    """

    curvature: Float[Array, "*h 2"] = parameter(unit="1", scale=0.05, typical=1.0, shape=(2,))
    pivot_scale: Float[Array, "*h 2"] = parameter(unit="1", scale=0.01, typical=0.01, shape=(2,))
    law: str = eqx.field(static=True, default="linear")

    NAME: typing.ClassVar[str] = "actuator_geometry"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("counts",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(curvature=zeros(dtype, 2), pivot_scale=zeros(dtype, 2), law=joint_law(inner))

    def fixed_parameter_fields(self) -> tuple[str, ...]:
        """A linear base fits the curvature, a base following the law the pivot scale."""
        return ("pivot_scale",) if self.law == "linear" else ("curvature",)

    def angle_correction(self, geometry, counts, angles, context, normal):
        act = geometry.actuators
        law = act.counts_to_angles(counts)
        line = geometry.linear_slope * counts + geometry.linear_intercept
        curved = self.curvature * (law - line)
        scaled = eqx.tree_at(lambda a: a.pivot_radius, act, act.pivot_radius * (1.0 + self.pivot_scale))
        pivot = scaled.counts_to_angles(counts) - law
        return curved + pivot


@typing.final
class Backlash(AbstractEffect):
    """Backlash (lost motion) of each axis's drive.

    Physical meaning: a drive with a dead band stops half of it short of the
    commanded position, behind the direction of its last motion. Where the dead
    band sits depends on the base's joint law (``law``, static, as
    :class:`~heliojax.effects.ActuatorGeometry`'s):

    * a base that maps counts to angles linearly (the Stone model, or an axis the
      plant declares ideal): a dead band of width ``w_i`` (rad) in the joint,
      correction ``-(w_i / 2) * s_i * approach_i`` with ``s_i =
      sign(linear_slope_i)`` the direction in which the joint angle grows with the
      counts;
    * a base that follows the linear actuator's law of cosines (the actuator
      model): the play of the spindle's nut, a dead band of width ``b_i`` (m) in the
      stroke, correction ``law_i(counts - approach_i * b_i / 2 * increment_i) -
      law_i(counts)`` with the nominal actuators: through the triangle the same
      lost stroke turns the joint by an angle that changes with the pose.

    ``approach_i`` is the sign (+1, -1; 0 unknown) of the last count change of axis
    ``i`` before the record (:class:`~heliojax.RecordContext` ``.approach``, from the
    chronological order of the records). A positive width is a lag.

    Parameters: ``backlash_1``, ``backlash_2`` (rad, the full dead-band width of the
    joint; linear law) or ``backlash_stroke_1``, ``backlash_stroke_2`` (m, of the
    stroke; actuator law); the other pair stays 0.
    Driving inputs: the approach directions. Residual signature: a step between
    records approached from below and from above (constant in the joint angle, or
    scaled by the triangle's lever), needs both directions in the data.
    """

    width: Float[Array, "*h 2"] = parameter(unit="rad", scale=1e-3, typical=3e-4, name="backlash", shape=(2,))
    stroke_width: Float[Array, "*h 2"] = parameter(
        unit="m", scale=3e-4, typical=1e-4, name="backlash_stroke", shape=(2,)
    )
    law: str = eqx.field(static=True, default="linear")

    NAME: typing.ClassVar[str] = "backlash"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("approach",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(width=zeros(dtype, 2), stroke_width=zeros(dtype, 2), law=joint_law(inner))

    def fixed_parameter_fields(self) -> tuple[str, ...]:
        """A linear base fits the joint's dead band, a base following the law the stroke's."""
        return ("stroke_width",) if self.law == "linear" else ("width",)

    def angle_correction(self, geometry, counts, angles, context, normal):
        if context is None:
            return None
        a = jnp.where(jnp.isfinite(context.approach), context.approach, 0.0)
        joint = -0.5 * self.width * jnp.sign(geometry.linear_slope) * a
        if self.law == "linear":
            return joint
        act = geometry.actuators
        lost = 0.5 * a * self.stroke_width * act.increment
        stroke = act.counts_to_angles(jnp.asarray(counts) - lost) - act.counts_to_angles(counts)
        ideal = -0.5 * self.stroke_width * act.increment * geometry.linear_slope * a
        return joint + jnp.where(geometry.ideal_axes, ideal, stroke)


@typing.final
class GravitySag(AbstractEffect):
    """Gravity sag of the mirror and its support.

    Physical meaning: the mirror's weight acts with a lever arm that is largest
    when the mirror stands vertical; the structure yields and the normal tips
    toward the horizon by ``g * cos(e_n)``, ``e_n`` the elevation of the mirror
    normal. Correction: the normal turns by ``-g cos(e_n)`` along the local
    direction of increasing elevation (in the vertical plane through the normal,
    whatever the chain), converted to joint angles through the chain's Jacobian
    (:meth:`~heliojax.effects.AbstractEffect.normal_tilt`).

    Parameter: ``gravity_sag`` (rad, the tip at a vertical mirror).
    Driving input: the mirror normal's elevation (from the pose; no record
    input). Residual signature: a smooth function of the elevation - under
    calibration sampling (a fixed target, so a limited range of normal
    elevations per heliostat) nearly linear in ``theta``, hence mostly absorbed
    by the base model's axis-1 offset and gear ratio.
    """

    sag: Float[Array, "*h"] = parameter(unit="rad", scale=1e-3, typical=1e-3, name="gravity_sag")

    NAME: typing.ClassVar[str] = "gravity_sag"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("normal_elevation",)
    TILTS_NORMAL: typing.ClassVar[bool] = True

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(sag=zeros(dtype))

    def normal_tilt(self, geometry, normal, context):
        del geometry, context
        up, cos_e = rising_direction(normal)
        return -self.sag * cos_e * up


@typing.final
class EncoderWobble(AbstractEffect):
    """n-per-revolution error of each axis (encoder eccentricity, gear runout).

    Physical meaning: an eccentric encoder disc or a gear with runout reads an
    angle off by a periodic function of the joint angle. Correction per axis
    ``i``: ``a_i cos(n angle_i) + b_i sin(n angle_i)``, ``angle_i`` the base
    model's joint angle, ``n`` cycles per revolution (static, default 2: an
    elliptic / two-lobed error; ``n = 1`` is a plain eccentricity, which over a
    calibration's range is mostly absorbed by offset and gear ratio).

    Parameters: ``wobble_cos_1, wobble_sin_1, wobble_cos_2, wobble_sin_2`` (rad);
    the amplitude of axis ``i`` is ``hypot(a_i, b_i)``.
    Driving inputs: the joint angles (from the counts). Residual signature: a
    sinusoid of ``n`` times each joint angle.
    """

    coefficients: Float[Array, "*h 4"] = parameter(
        unit="rad", scale=1e-3, typical=3e-4, name="wobble", shape=(4,), suffixes=("cos_1", "sin_1", "cos_2", "sin_2")
    )
    n: int = eqx.field(static=True, default=2)

    def __init__(self, a: Float[Array, "2"], b: Float[Array, "2"], n: int = 2):
        a = jnp.asarray(a)
        b = jnp.asarray(b)
        self.coefficients = jnp.stack([a[0], b[0], a[1], b[1]])
        self.n = n

    @property
    def a(self) -> Float[Array, "2"]:
        """Cosine amplitudes ``(a_1, a_2)`` (rad)."""
        return self.coefficients[jnp.array([0, 2])]

    @property
    def b(self) -> Float[Array, "2"]:
        """Sine amplitudes ``(b_1, b_2)`` (rad)."""
        return self.coefficients[jnp.array([1, 3])]

    NAME: typing.ClassVar[str] = "encoder_wobble"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("joint_angles",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(a=zeros(dtype, 2), b=zeros(dtype, 2))

    def angle_correction(self, geometry, counts, angles, context, normal):
        return self.a * jnp.cos(self.n * angles) + self.b * jnp.sin(self.n * angles)
