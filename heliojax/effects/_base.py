"""The effect mechanism: an effect wraps a base kinematic model.

An *effect* is a small :class:`equinox.Module` holding its own physical
parameters. It acts on one or more stages of a calibration record's
prediction, through hooks that default to the identity:

1. ``adjust_geometry`` - the heliostat's surveyed geometry (position);
2. ``angle_correction`` - an additive correction ``(2,)`` (rad) to the joint
   angles ``(theta, tau)`` the base model computes from the motor counts; it
   sees the base angles, the counts, the record context and (when
   ``NEEDS_NORMAL``) the mirror normal of the uncorrected pose;
   ``normal_tilt`` - an additive change ``(3,)`` of the mirror normal in space,
   turned into joint angles through the chain's Jacobian;
3. ``adjust_sun`` - the sun direction the model believes in;
4. ``adjust_focal`` - the measured focal spot (target survey).

:class:`EffectModel` ``(inner, effects)`` is again an
:class:`~heliojax.AbstractKinematicModel` (a wrapper of its inner model), so
fitting, metrics and the simulator never special-case effects, and it composes
with any other wrapper (the neural correction, another EffectModel) in any
order. With all effect parameters zero an :class:`EffectModel` predicts exactly
what its inner model predicts. An effect's parameters are fields declared with
:func:`heliojax.parameter` (units, solver scale and typical size in the field
metadata); data-derived constants with :func:`heliojax.reference`.

Missing record inputs (``NaN`` weather or time, approach ``0``, or no context at
all, as when a controller inverts the model) switch the corresponding
correction off for that record; inputs are sanitised *before* any arithmetic
so no NaN reaches a value or a gradient.
"""

from __future__ import annotations

import collections.abc
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._heliostat import HeliostatGeometry, RecordContext, chain_pose
from .._kinematics import AbstractKinematicModel, AbstractModelWrapper
from .._parameters import check_fields


class AbstractEffect(eqx.Module):
    """One physical effect: its parameters (fields), meaning, driving inputs and hooks.

    Class attributes (documentation):
        NAME: the effect's name (one of :data:`heliojax.effects.EFFECT_NAMES`).
        DRIVERS: names of the record inputs the effect needs.
        NEEDS_NORMAL: whether :meth:`angle_correction` uses the mirror normal.
        TILTS_NORMAL: whether :meth:`normal_tilt` is overridden (the model then
            computes the chain's Jacobian of the normal in the joint angles).
    """

    NAME: typing.ClassVar[str] = ""
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ()
    NEEDS_NORMAL: typing.ClassVar[bool] = False
    TILTS_NORMAL: typing.ClassVar[bool] = False

    def __check_init__(self):
        # concrete values only (discovery builds effects inside traced code): a NaN or
        # inf parameter had made every prediction NaN, only make_effect checked them
        check_fields(self)

    @classmethod
    def nominal(cls, inner: AbstractKinematicModel | None, dtype: typing.Any = None) -> AbstractEffect:
        """The effect with every parameter at its no-effect value (references at
        their defaults), for a model wrapping ``inner``."""
        raise NotImplementedError

    def driven(self, fleet: typing.Any) -> np.ndarray | None:
        """Per parameter element (the effect's :class:`~heliojax.ParameterView`
        order), whether ``fleet``'s valid records can determine it at all; None: every
        element. Discovery fixes the others at their no-effect value, so they enter
        neither its fits nor its parameter counts (e.g. the offset of a target no
        record was measured on)."""
        del fleet
        return None

    # -- hooks (identity by default) ----------------------------------------------

    def adjust_geometry(self, geometry: HeliostatGeometry) -> HeliostatGeometry:
        return geometry

    def angle_correction(
        self,
        geometry: HeliostatGeometry,
        counts: Float[Array, "2"],
        angles: Float[Array, "2"],
        context: RecordContext | None,
        normal: Float[Array, "3"] | None,
    ) -> Float[Array, "2"] | None:
        """Additive joint-angle correction (rad), or None for none."""
        del geometry, counts, angles, context, normal
        return None

    def normal_tilt(
        self, geometry: HeliostatGeometry, normal: Float[Array, "3"], context: RecordContext | None
    ) -> Float[Array, "3"] | None:
        """Additive change (rad, tangent to the unit sphere at ``normal``) of the
        mirror normal, or None. The model turns it into joint-angle corrections by
        least squares through the chain's Jacobian ``d normal / d angles``, so an
        effect that acts on the normal in space (gravity acts vertically) is
        written once for every kinematic chain."""
        del geometry, normal, context
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


def rising_direction(normal: Float[Array, "3"]) -> tuple[Float[Array, "3"], Float[Array, ""]]:
    """``(up, cos_e)``: the unit vector tangent to the sphere at the unit ``normal``
    along which its elevation grows (``(z - (z . n) n) / cos e``, in the vertical plane
    through the normal) and ``cos e``, ``e`` the normal's elevation (kept from 0 for a
    vertical normal)."""
    horizontal_sq = normal[0] ** 2 + normal[1] ** 2
    cos_e = jnp.sqrt(jnp.clip(horizontal_sq, 1e-30, 1.0))
    return jnp.stack([-normal[2] * normal[0], -normal[2] * normal[1], horizontal_sq]) / cos_e, cos_e


def joint_law(inner: AbstractKinematicModel | None) -> str:
    """The joint law of the base model under ``inner`` (its wrappers looked through):
    ``"linear"`` (counts to angles by a line, the Stone model; also for ``None``) or
    ``"actuator"`` (the linear actuator's law of cosines)."""
    base = inner.base if isinstance(inner, AbstractModelWrapper) else inner
    return getattr(base, "JOINT_LAW", "linear")


def zeros(dtype: typing.Any, *shape: int) -> Float[Array, "..."]:
    """A zero parameter of ``shape`` (no-effect value)."""
    return jnp.zeros(shape, dtype)


@typing.final
class EffectModel(AbstractModelWrapper):
    """A kinematic model extended by effects.

    Attributes:
        inner: the wrapped model (a base model such as
            :class:`~heliojax.StoneModel` or :class:`~heliojax.ActuatorModel`, or
            another wrapper).
        effects: the effects, applied in the order given (their joint-angle
            corrections add up; sun and focal-spot adjustments compose).

    :meth:`counts` inverts the inner map only (controllers aim with the model
    without effects); :meth:`joint_angles` includes the context-free angle corrections.
    """

    inner: AbstractKinematicModel
    effects: tuple[AbstractEffect, ...]

    def __check_init__(self):
        for e in self.effects:
            if not isinstance(e, AbstractEffect):
                raise TypeError(f"EffectModel: {e!r} is not an AbstractEffect")
        names = [e.NAME for e in self.effects]
        if len(set(names)) != len(names):
            raise ValueError(f"EffectModel: repeated effect in {names}")

    def label(self) -> str:
        return "+".join([self.inner.label(), *(e.NAME for e in self.effects)])

    @property
    def effect_names(self) -> tuple[str, ...]:
        return tuple(e.NAME for e in self.effects)

    def adjusted_geometry(self, geometry):
        g = self.inner.adjusted_geometry(geometry)
        for e in self.effects:
            g = e.adjust_geometry(g)
        return g

    def corrected_angles(self, geometry, counts, angles, context) -> Float[Array, "2"]:
        """The inner model's joint ``angles`` (rad) of one record plus every effect's
        correction (``geometry`` already adjusted)."""
        normal = None
        tilts = self.inner.tilts()
        if any(e.NEEDS_NORMAL or e.TILTS_NORMAL for e in self.effects):
            normal = chain_pose(tilts, angles, geometry).normal
        total = angles
        for e in self.effects:
            d = e.angle_correction(geometry, counts, angles, context, normal)
            if d is not None:
                total = total + d
        if any(e.TILTS_NORMAL for e in self.effects):
            assert normal is not None
            dn = sum(
                (t for t in (e.normal_tilt(geometry, normal, context) for e in self.effects) if t is not None),
                jnp.zeros(3, normal.dtype),
            )
            jac = jax.jacfwd(lambda a: chain_pose(tilts, a, geometry).normal)(angles)  # (3, 2)
            total = total + jnp.linalg.solve(jac.T @ jac, jac.T @ dn)
        return total

    def record_angles(self, geometry, counts, context):
        angles = self.inner.record_angles(geometry, counts, context)
        return self.corrected_angles(geometry, counts, angles, context)

    def joint_angles(self, geometry, counts):
        return self.record_angles(geometry, jnp.asarray(counts), None)

    def sun(self, geometry, context):
        s = self.inner.sun(geometry, context)
        for e in self.effects:
            s = e.adjust_sun(s, context)
        return s

    def spot(self, focal_spot, context):
        f = self.inner.spot(focal_spot, context)
        for e in self.effects:
            f = e.adjust_focal(f, context)
        return f


def add_effects(model: AbstractKinematicModel, effects: collections.abc.Sequence[AbstractEffect]) -> EffectModel:
    """``model`` with ``effects`` appended (extends an :class:`EffectModel`'s own list)."""
    if isinstance(model, EffectModel):
        return EffectModel(model.inner, tuple(model.effects) + tuple(effects))
    return EffectModel(model, tuple(effects))
