"""The effect mechanism: an effect wraps a base kinematic model.

An *effect* is a small :class:`equinox.Module` holding its own physical
parameters. It acts on one or more stages of a calibration record's
prediction, through hooks that default to the identity:

1. ``adjust_geometry`` - the heliostat's surveyed geometry (position);
2. ``angle_correction`` - an additive correction ``(2,)`` (rad) to the joint
   angles ``(theta, tau)`` the base model computes from the motor counts; it
   sees the base angles, the counts, the record context and (when
   ``NEEDS_NORMAL``) the mirror normal of the uncorrected pose;
3. ``adjust_sun`` - the sun direction the model believes in;
4. ``adjust_focal`` - the measured focal spot (target survey).

:class:`EffectModel` ``(base, effects)`` is again an
:class:`~heliojax.AbstractKinematicModel`, so fitting, metrics and the
simulator never special-case effects. With all effect parameters zero an
:class:`EffectModel` predicts exactly what its base predicts.

Missing record inputs (``NaN`` weather or time, approach ``0``, or no context at
all, as when a controller inverts the model) switch the corresponding
correction off for that record; inputs are sanitised *before* any arithmetic
so no NaN reaches a value or a gradient.
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._kinematics import (
    AbstractKinematicModel,
    HeliostatGeometry,
    Pose,
    RecordContext,
    beam_error_components,
    beam_pointing_error,
    chain_pose,
)


class AbstractEffect(eqx.Module):
    """One physical effect: its parameters, meaning, driving inputs and hooks.

    Class attributes (documentation and model-spec construction):
        NAME: the effect's name (one of :data:`heliojax.effects.EFFECT_NAMES`).
        PARAM_NAMES: fitted parameters, in vector order (see :meth:`param_names`).
        PARAM_UNITS: unit label per parameter.
        PARAM_SCALES: the solver's unit per parameter (1 scaled unit changes the
            beam by roughly 1 mrad).
        TYPICAL_SIZES: a realistic physical size per parameter, documented a
            priori; discovery judges the identifiability of strongly collinear
            candidates at this size (:mod:`heliojax.discovery._identifiability`).
        REFERENCE_NAMES: constants derived from the data (not fitted), such as a
            reference temperature; :meth:`reference_defaults` gives defaults.
        DRIVERS: names of the record inputs the effect needs.
        NEEDS_NORMAL: whether :meth:`angle_correction` uses the mirror normal.
    """

    NAME: typing.ClassVar[str] = ""
    PARAM_NAMES: typing.ClassVar[tuple[str, ...]] = ()
    PARAM_UNITS: typing.ClassVar[tuple[str, ...]] = ()
    PARAM_SCALES: typing.ClassVar[tuple[float, ...]] = ()
    TYPICAL_SIZES: typing.ClassVar[tuple[float, ...]] = ()
    REFERENCE_NAMES: typing.ClassVar[tuple[str, ...]] = ()
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ()
    NEEDS_NORMAL: typing.ClassVar[bool] = False

    # -- parameters ---------------------------------------------------------------

    @classmethod
    def param_names(cls, base_kind: str = "stone8") -> tuple[str, ...]:
        """Fitted parameter names for a base model kind (most effects ignore it)."""
        del base_kind
        return cls.PARAM_NAMES

    @classmethod
    def param_units(cls, base_kind: str = "stone8") -> tuple[str, ...]:
        del base_kind
        return cls.PARAM_UNITS

    @classmethod
    def param_scales(cls, base_kind: str = "stone8") -> tuple[float, ...]:
        del base_kind
        return cls.PARAM_SCALES

    @classmethod
    def typical_sizes(cls, base_kind: str = "stone8") -> tuple[float, ...]:
        del base_kind
        return cls.TYPICAL_SIZES

    @classmethod
    def reference_defaults(cls) -> tuple[float, ...]:
        """Default values of the references (used when the data cannot set them)."""
        return ()

    @classmethod
    def from_vector(cls, params, references, base_kind: str = "stone8") -> "AbstractEffect":
        """The effect from its parameter vector (order :meth:`param_names`) and
        its reference vector (order ``REFERENCE_NAMES``)."""
        raise NotImplementedError

    def to_vector(self, base_kind: str = "stone8") -> Float[Array, " k"]:
        """The parameter vector (inverse of :meth:`from_vector`)."""
        raise NotImplementedError

    # -- hooks (identity by default) ----------------------------------------------

    def adjust_geometry(self, geometry: HeliostatGeometry) -> HeliostatGeometry:
        return geometry

    def angle_correction(
        self,
        base: AbstractKinematicModel,
        geometry: HeliostatGeometry,
        counts: Float[Array, "2"],
        angles: Float[Array, "2"],
        context: RecordContext | None,
        normal: Float[Array, "3"] | None,
    ) -> Float[Array, "2"] | None:
        """Additive joint-angle correction (rad), or None for none."""
        del base, geometry, counts, angles, context, normal
        return None

    def adjust_sun(self, sun: Float[Array, "3"], context: RecordContext) -> Float[Array, "3"]:
        del context
        return sun

    def adjust_focal(self, focal_spot: Float[Array, "3"], context: RecordContext) -> Float[Array, "3"]:
        del context
        return focal_spot


def known(x, fill):
    """``x`` where finite, else ``fill`` (sanitise an input *before* arithmetic)."""
    x = jnp.asarray(x)
    return jnp.where(jnp.isfinite(x), x, fill)


@typing.final
class EffectModel(AbstractKinematicModel):
    """A base kinematic model extended by effects.

    Attributes:
        base: the base model (:class:`~heliojax.StoneModel`,
            :class:`~heliojax.ActuatorModel`, ...), whose pose is the standard
            rotation chain :func:`heliojax._kinematics.chain_pose`.
        effects: the effects, applied in the order given (their joint-angle
            corrections add up; sun and focal-spot adjustments compose).

    :meth:`counts` inverts the *base* map only (controllers aim with the base
    model); :meth:`joint_angles` includes the context-free angle corrections.
    """

    base: AbstractKinematicModel
    effects: tuple[AbstractEffect, ...]

    def __check_init__(self):
        if isinstance(self.base, EffectModel):
            raise ValueError("EffectModel: nest effects with add_effects(model, effects), not by wrapping twice")
        for e in self.effects:
            if not isinstance(e, AbstractEffect):
                raise TypeError(f"EffectModel: {e!r} is not an AbstractEffect")

    def tilts(self):
        return self.base.tilts()

    def _geometry(self, geometry):
        for e in self.effects:
            geometry = e.adjust_geometry(geometry)
        return geometry

    def _angles(self, geometry, counts, context):
        angles = self.base.joint_angles(geometry, counts)
        normal = None
        if any(e.NEEDS_NORMAL for e in self.effects):
            normal = chain_pose(self.base.tilts(), angles, geometry).normal
        total = angles
        for e in self.effects:
            d = e.angle_correction(self.base, geometry, counts, angles, context, normal)
            if d is not None:
                total = total + d
        return total

    def joint_angles(self, geometry, counts):
        return self._angles(geometry, jnp.asarray(counts), None)

    def counts(self, geometry, angles):
        return self.base.counts(geometry, angles)

    def pose(self, geometry, counts, context=None) -> Pose:
        g = self._geometry(geometry)
        angles = self._angles(g, jnp.asarray(counts), context)
        return chain_pose(self.base.tilts(), angles, g)

    def sun(self, geometry, context):
        s = self.base.sun(geometry, context)
        for e in self.effects:
            s = e.adjust_sun(s, context)
        return s

    def _focal(self, focal_spot, context):
        f = jnp.asarray(focal_spot)
        for e in self.effects:
            f = e.adjust_focal(f, context)
        return f

    def beam_components(self, geometry, counts, context, focal_spot):
        return beam_error_components(
            self.pose(geometry, counts, context), self.sun(geometry, context), self._focal(focal_spot, context)
        )

    def beam_error(self, geometry, counts, context, focal_spot):
        return beam_pointing_error(
            self.pose(geometry, counts, context), self.sun(geometry, context), self._focal(focal_spot, context)
        )


def add_effects(model: AbstractKinematicModel, effects: typing.Sequence[AbstractEffect]) -> EffectModel:
    """``model`` with ``effects`` appended (flattens an :class:`EffectModel`)."""
    if isinstance(model, EffectModel):
        return EffectModel(model.base, tuple(model.effects) + tuple(effects))
    return EffectModel(model, tuple(effects))
