"""Environmental, time and sun effects: thermal expansion, wind load, clock error,
drift and steps of the joint zeros, atmospheric refraction."""

from __future__ import annotations

import math
import typing

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._parameters import parameter, reference as data_reference
from ._base import AbstractEffect, joint_law, known, rising_direction, zeros

SOLAR_RATE_RAD_S = 2.0 * math.pi / 86400.0
"""Rate of the sun's hour angle (rad/s): one turn per mean solar day."""

DEFAULT_LATITUDE_DEG = 50.913421122592574
"""Latitude of the Jülich solar tower (PAINT plant reference), the default of :class:`Clock`."""


@typing.final
class Thermal(AbstractEffect):
    """Thermal expansion of the drives and the structure.

    Physical meaning: the actuator, its mounts and the pylon expand with the
    ambient temperature ``T``. A change of a fixed length (a lever, a mount)
    turns each joint by a constant angle per kelvin (steel: ~12e-6/K on ~0.3 m
    gives ~0.01 mrad/K); the spindle of a linear actuator expands in proportion
    to its extended length. Correction::

        angle_i += k_i (T - T_ref) + e_i

    with the spindle's part ``e_i`` depending on the base's joint law (``law``,
    static, as :class:`~heliojax.effects.ActuatorGeometry`'s):

    * a base that maps counts to angles linearly (the Stone model, or an axis the
      plant declares ideal): the expansion acts like a change of the gear ratio,
      ``e_i = s_i angle_i (T - T_ref)`` (first order), with ``angle_i`` the base
      model's joint angle (rad);
    * a base that follows the linear actuator's law of cosines (the actuator
      model): the whole stroke grows by the factor ``1 + s_i (T - T_ref)``, and
      ``e_i = law_i(counts; stroke x (1 + s_i (T - T_ref))) - law_i(counts)`` with
      the nominal actuators (as :class:`~heliojax.effects.ActuatorGeometry`'s pivot
      scale: the base's small increment / stroke corrections change it by a
      second-order amount). Through the triangle, a longer stroke turns the joint
      by an amount that is neither constant nor proportional to the angle, which
      the gear-ratio form leaves as a curved remainder in the counts.

    Parameters: ``thermal_1``, ``thermal_2`` (rad/K), ``thermal_scale_1``,
    ``thermal_scale_2`` (1/K; typical: steel's 12e-6/K). Reference:
    ``thermal_reference_c`` (deg C; the data's mean temperature, so the
    coefficients do not trade off against the base model's offsets).
    Driving input: ``temperature`` (records without one get no correction).
    Residual signature: proportional to ``T - T_ref`` on each axis, growing with
    the stroke for the spindle's part.
    """

    coefficient: Float[Array, "*h 2"] = parameter(unit="rad/K", scale=1e-4, typical=1.5e-5, name="thermal", shape=(2,))
    expansion: Float[Array, "*h 2"] = parameter(
        unit="1/K", scale=1e-4, typical=1.2e-5, name="thermal_scale", shape=(2,)
    )
    reference: Float[Array, ""] = data_reference(unit="deg C", default=20.0, name="thermal_reference_c")
    law: str = eqx.field(static=True, default="linear")

    NAME: typing.ClassVar[str] = "thermal"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("temperature",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(
            coefficient=zeros(dtype, 2),
            expansion=zeros(dtype, 2),
            reference=jnp.asarray(20.0, dtype),
            law=joint_law(inner),
        )

    def angle_correction(self, geometry, counts, angles, context, normal):
        if context is None:
            return None
        dt = known(context.temperature, self.reference) - self.reference
        gear = self.expansion * angles * dt
        if self.law == "linear":
            return self.coefficient * dt + gear
        act = geometry.actuators
        spindle = act.counts_to_angles(counts, 1.0 + self.expansion * dt) - act.counts_to_angles(counts)
        return self.coefficient * dt + jnp.where(geometry.ideal_axes, gear, spindle)


@typing.final
class Wind(AbstractEffect):
    """Wind load on the mirror.

    Physical meaning: the dynamic pressure ``rho v^2 / 2`` on the mirror bends
    the structure and the drives. A wind blowing onto the mirror's face pushes
    it over its elevation axis; a cross wind turns it about the vertical axis;
    and a load that does not depend on where the wind comes from (the drag's
    mean over directions, buffeting, a structure that yields downward under any
    load) tips the normal toward the horizon. The load as a function of the
    wind's direction relative to the mirror, to its first harmonic::

        theta += c_1 v^2 cos(phi - a_n)        tau += c_2 v^2 sin(phi - a_n)
        the normal tips toward the horizon by c_0 v^2

    with ``v`` the wind speed (m/s), ``phi`` the direction the wind comes from
    (clockwise from north) and ``a_n`` the azimuth (clockwise from north) the
    mirror normal faces. The tip ``c_0 v^2`` turns the normal in the vertical
    plane through it (as :class:`~heliojax.effects.GravitySag` does, whatever
    the chain); a yaw that does not depend on the direction has no cause and is
    left out.

    Parameters: ``wind_1``, ``wind_2``, ``wind_droop`` (rad per (m/s)^2).
    Driving inputs: ``wind_speed``, ``wind_direction`` and the pose (the tip:
    ``wind_speed`` and the pose).
    Residual signature: grows with ``v^2``, sign and axis set by the wind's
    direction relative to the mirror, plus a tip toward the horizon.
    """

    coefficient: Float[Array, "*h 2"] = parameter(unit="rad/(m/s)^2", scale=1e-5, typical=5e-6, name="wind", shape=(2,))
    droop: Float[Array, "*h"] = parameter(unit="rad/(m/s)^2", scale=1e-5, typical=5e-6, name="wind_droop")

    NAME: typing.ClassVar[str] = "wind"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("wind_speed", "wind_direction")
    NEEDS_NORMAL: typing.ClassVar[bool] = True
    TILTS_NORMAL: typing.ClassVar[bool] = True

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(coefficient=zeros(dtype, 2), droop=zeros(dtype))

    def normal_tilt(self, geometry, normal, context):
        del geometry
        if context is None:
            return None
        v = known(context.wind_speed, 0.0)
        up, _ = rising_direction(normal)
        return -self.droop * v * v * up

    def angle_correction(self, geometry, counts, angles, context, normal):
        if context is None:
            return None
        ok = jnp.isfinite(context.wind_speed) & jnp.isfinite(context.wind_direction)
        v = jnp.where(ok, context.wind_speed, 0.0)
        phi = jnp.where(ok, context.wind_direction, 0.0)
        assert normal is not None  # NEEDS_NORMAL: the model passes the pose's normal
        facing = jnp.arctan2(normal[0], normal[1])
        rel = phi - facing
        v2 = v * v
        return self.coefficient * jnp.stack([v2 * jnp.cos(rel), v2 * jnp.sin(rel)])


def rotate_about(v, axis, angle):
    """Rodrigues rotation of vector ``v`` about unit ``axis`` by ``angle`` (rad)."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return v * c + jnp.cross(axis, v) * s + axis * jnp.dot(axis, v) * (1.0 - c)


@typing.final
class Clock(AbstractEffect):
    """Clock error of the controller: offset and drift of the time it computes the
    sun with.

    Physical meaning: the controller's clock reads ``t + dt`` at true time
    ``t``, with ``dt = offset + drift * (t - t_ref) / 86400``; the sun direction
    the model should compare with is the sun at the clock's time. The sun's
    hour angle grows at :data:`SOLAR_RATE_RAD_S`, i.e. the sky turns about the
    celestial pole, so the sun at ``t + dt`` is the recorded sun turned by
    ``-SOLAR_RATE_RAD_S * dt`` about the polar axis ``(0, cos lat, sin lat)``
    (ENU); this equals re-evaluating the solar-position code at ``t + dt`` to
    ~3e-3 relative (the declination's change, < 0.4 deg/day, is neglected; the
    tests compare with :func:`heliojax.solar_position`).

    Parameters: ``clock_offset`` (s), ``clock_drift`` (s/day). References:
    ``clock_reference_s`` (unix s; the data's mean time) and
    ``clock_latitude_deg`` (the plant's latitude).
    Driving inputs: ``unix_time`` (records without a time get no correction)
    and the sun. Residual signature: a turn of the sun about the polar axis,
    growing linearly with time (drift); a constant turn (offset) is largely
    absorbed by the base model's tilts.
    """

    offset: Float[Array, "*h"] = parameter(unit="s", scale=10.0, typical=10.0, name="clock_offset")
    drift: Float[Array, "*h"] = parameter(unit="s/day", scale=0.1, typical=0.1, name="clock_drift")
    reference: Float[Array, ""] = data_reference(unit="s", default=1.65e9, name="clock_reference_s")
    latitude_deg: Float[Array, ""] = data_reference(unit="deg", default=DEFAULT_LATITUDE_DEG, name="clock_latitude_deg")

    NAME: typing.ClassVar[str] = "clock"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("unix_time",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(
            offset=zeros(dtype),
            drift=zeros(dtype),
            reference=jnp.asarray(1.65e9, dtype),
            latitude_deg=jnp.asarray(DEFAULT_LATITUDE_DEG, dtype),
        )

    def clock_error(self, unix_time) -> Float[Array, "..."]:
        """``dt`` (s) at ``unix_time`` (0 where the time is unknown)."""
        t = known(unix_time, self.reference)
        return jnp.where(
            jnp.isfinite(jnp.asarray(unix_time)), self.offset + self.drift * (t - self.reference) / 86400.0, 0.0
        )

    def adjust_sun(self, sun, context):
        lat = jnp.deg2rad(self.latitude_deg)
        axis = jnp.stack([jnp.zeros_like(lat), jnp.cos(lat), jnp.sin(lat)])
        return rotate_about(sun, axis, -SOLAR_RATE_RAD_S * self.clock_error(context.unix_time))


YEAR_S = 365.25 * 86400.0
"""One Julian year (s): the time unit of :class:`OffsetDrift`'s rates."""


@typing.final
class OffsetDrift(AbstractEffect):
    """Slow drift of the joint zeros: creep of the drives, settling of the
    foundation, wear.

    Physical meaning: each joint's zero moves at a constant rate, so the joint
    angle the base model computes from the counts is off by an amount that grows
    linearly with time. Correction::

        angle_i += r_i (t - t_ref) / year

    with ``angle_i`` the base model's joint angle (rad) and ``t`` the record's
    time. A step (maintenance) is not this effect but a change point; a clock
    error is not either (it turns the *sun* about the polar axis: its residual
    depends on the sun's motion, this one does not).

    Parameters: ``offset_drift_1``, ``offset_drift_2`` (rad/year). Reference:
    ``offset_drift_reference_s`` (unix s; the data's mean time, so the rates do
    not trade off against the base model's offsets).
    Driving input: ``unix_time`` (records without one get no correction).
    Residual signature: on each axis a constant offset growing linearly with time,
    whatever the pose.
    """

    rate: Float[Array, "*h 2"] = parameter(unit="rad/year", scale=1e-3, typical=1e-3, name="offset_drift", shape=(2,))
    reference: Float[Array, ""] = data_reference(unit="s", default=1.65e9, name="offset_drift_reference_s")

    NAME: typing.ClassVar[str] = "offset_drift"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("unix_time",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(rate=zeros(dtype, 2), reference=jnp.asarray(1.65e9, dtype))

    def angle_correction(self, geometry, counts, angles, context, normal):
        if context is None:
            return None
        t = known(context.unix_time, self.reference)
        return self.rate * ((t - self.reference) / YEAR_S)


@typing.final
class OffsetStep(AbstractEffect):
    """A step of the joint zeros at a known date: maintenance (an axis re-zeroed,
    a drive exchanged), the change point of :func:`heliojax.fitting.find_change_points`.

    Physical meaning: before the change time ``t_c`` the joint zeros were
    ``jump`` below what they are now, so the model's own axis offsets describe the
    heliostat's *current* state and the records before the change are corrected::

        angle_i -= jump_i       for t < t_c

    ``jump`` is "later minus earlier", the convention of the change-point scan.
    Records without a time, and every pose a controller inverts (no record
    context), get no correction: they are the current state. The model aims as
    the heliostat is now; the records from before the step still determine its
    geometry (only the zeros moved). ``t_c = 0`` (before any timed record) means
    no step.

    Parameters: ``change_point_jump_1``, ``_2`` (rad; typical: the axis offsets'
    own 1e-2, a re-zeroing error being an offset error); ``change_point_time``
    (unix s; the date the scan found, not fitted: its likelihood is a step function
    of ``t_c``, which no gradient method can fit).
    Driving input: ``unix_time``.
    Residual signature: a constant offset of both axes on every record before one
    date, whatever the pose. Not one of :data:`heliojax.effects.EFFECT_NAMES`: discovery
    adds it where its change-point scan reports a step, it does not screen it.
    """

    jump: Float[Array, "*h 2"] = parameter(unit="rad", scale=1e-3, typical=1e-2, name="change_point_jump", shape=(2,))
    time: Float[Array, "*h"] = parameter(unit="s", scale=86400.0, name="change_point_time")

    NAME: typing.ClassVar[str] = "change_point"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("unix_time",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(jump=zeros(dtype, 2), time=jnp.zeros((), dtype))

    def fixed_parameter_fields(self) -> tuple[str, ...]:
        """The change time is found by a scan over the record dates, never fitted."""
        return ("time",)

    def angle_correction(self, geometry, counts, angles, context, normal):
        if context is None:
            return None
        before = known(context.unix_time, jnp.inf) < self.time  # no time: the current state
        return jnp.where(before, -self.jump, jnp.zeros_like(self.jump))


def standard_refraction(elevation: Float[Array, "..."]) -> Float[Array, "..."]:
    """Atmospheric refraction (rad) of a body at true elevation ``elevation`` (rad)
    at 1010 hPa and 10 deg C: Saemundsson's formula
    ``R = 1.02 / tan(h + 10.3 / (h + 5.11))`` arcmin, ``h`` in degrees
    (0.29 mrad at 45 deg, 1.57 mrad at 10 deg, 0 at the zenith). Elevations
    below -0.5 deg are clipped."""
    h = jnp.maximum(jnp.rad2deg(elevation), -0.5)
    r_arcmin = 1.02 / jnp.tan(jnp.deg2rad(h + 10.3 / (h + 5.11)))
    return jnp.deg2rad(jnp.maximum(r_arcmin, 0.0) / 60.0)


@typing.final
class Refraction(AbstractEffect):
    """Atmospheric refraction of the apparent sun, wrongly or not applied.

    Physical meaning: the atmosphere lifts the apparent sun by the refraction
    ``R(e)`` (:func:`standard_refraction`, a few mrad near the horizon,
    ~0.3 mrad at 45 deg). If the recorded sun positions lack it (or apply it
    twice, or at the wrong pressure), the beam errors carry a multiple of
    ``R(e)``. Correction: the model's sun is lifted in its vertical plane by
    ``kappa * R(e)``.

    Parameter: ``refraction_scale`` (dimensionless; 1 = the full standard
    refraction is missing). Driving input: the sun elevation. Residual
    signature: vertical, growing steeply toward low elevations (~cot e).
    """

    scale: Float[Array, "*h"] = parameter(unit="1", scale=1.0, typical=1.0, name="refraction_scale")

    NAME: typing.ClassVar[str] = "refraction"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("sun_elevation",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(scale=zeros(dtype))

    def adjust_sun(self, sun, context):
        horizontal = jnp.sqrt(jnp.clip(sun[0] ** 2 + sun[1] ** 2, 1e-30))
        el = jnp.arctan2(sun[2], horizontal)
        new_el = el + self.scale * standard_refraction(el)
        h = sun[:2] / horizontal
        return jnp.concatenate([h * jnp.cos(new_el), jnp.sin(new_el)[None]])
