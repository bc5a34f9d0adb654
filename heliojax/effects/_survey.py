"""Survey errors: the heliostat's or a target's surveyed position is off."""

from __future__ import annotations

import typing

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._parameters import parameter
from ._base import AbstractEffect, zeros


@typing.final
class SurveyHeliostat(AbstractEffect):
    """Survey error of the heliostat's position.

    Physical meaning: the heliostat stands at ``P + d`` instead of its surveyed
    position ``P``. Correction: the geometry's ``position`` is moved by ``d``
    (ENU m), which moves the mirror centre and so the direction to the target.

    Parameters: ``survey_heliostat_e``, ``_n``, ``_u`` (m).
    Driving input: none but the geometry. Residual signature: a change of the
    direction from the mirror to the (fixed) target - nearly constant for one
    heliostat, hence largely absorbed by the base model's tilts; identifiable
    only through the small variation of the mirror centre with the pose.
    """

    delta: Float[Array, "*h 3"] = parameter(
        unit="m", scale=0.1, typical=0.05, name="survey_heliostat", shape=(3,), suffixes=("e", "n", "u")
    )

    NAME: typing.ClassVar[str] = "survey_heliostat"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ()

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(delta=zeros(dtype, 3))

    def adjust_geometry(self, geometry):
        return eqx.tree_at(lambda g: g.position, geometry, geometry.position + self.delta)


TARGET_SLOTS = 4
"""Target slots ``T`` of :class:`SurveyTarget`: the fleet's targets in
``Fleet.target_names`` order (index = ``RecordContext.target``). Four: the
Juelich tower's three planar calibration targets (``solar_tower_juelich_lower``,
``solar_tower_juelich_upper``, ``multi_focus_tower``) and one spare. Records on a
later target get no correction (as records with an unknown target, -1)."""


@typing.final
class SurveyTarget(AbstractEffect):
    """Survey errors of the calibration targets, one per target.

    Physical meaning: each calibration target was surveyed on its own, so target
    ``k`` (and every focal spot measured on it) is at ``+ d_k`` (ENU m) from where
    the data place it. Correction: the focal spot the model compares with is the
    recorded one moved by the offset of the record's target,
    ``spot + d[context.target]``; a record whose target is unknown (``-1``) or
    beyond the :data:`TARGET_SLOTS` slots is not corrected.

    Parameters: ``delta`` ``(T, 3)`` = ``(TARGET_SLOTS, 3)`` ENU m, named
    ``survey_target_<k>_e``, ``_n``, ``_u`` for slot ``k = 1..T`` (target
    ``k - 1`` of ``Fleet.target_names``); physically one value per target for
    all heliostats that use it (the shared form). A slot no record of a fleet
    uses is not determined by its data: discovery fixes it at 0
    (:meth:`driven`), so it enters neither the fit nor the BIC.
    Driving input: the record's target (``RecordContext.target``). Residual
    signature: a fixed displacement on each target, i.e. a beam error of
    ``d_perp / distance`` in a direction fixed per heliostat and target. A shift
    common to every target a heliostat uses is nearly a fixed rotation of its beam,
    largely absorbed by its tilts; what the records determine is mainly the
    *differences* between the targets' offsets (measured where heliostats use
    several targets), so the reported offsets are known up to a poorly
    determined common part.
    """

    delta: Float[Array, "*h T 3"] = parameter(
        unit="m",
        scale=0.1,
        typical=0.05,
        name="survey_target",
        shape=(TARGET_SLOTS, 3),
        suffixes=("e", "n", "u"),
    )

    NAME: typing.ClassVar[str] = "survey_target"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ("target",)

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(delta=zeros(dtype, TARGET_SLOTS, 3))

    def driven(self, fleet) -> np.ndarray:
        """``(T * 3,)`` the slots the fleet's valid records use (each of its 3 elements)."""
        k = np.asarray(fleet.target_index)[np.asarray(fleet.mask, bool)]
        used = np.isin(np.arange(TARGET_SLOTS), k)
        return np.repeat(used, 3)

    def adjust_focal(self, focal_spot, context):
        if context is None:
            return focal_spot
        k = jnp.asarray(context.target)
        known = (k >= 0) & (k < TARGET_SLOTS)
        d = self.delta[jnp.where(known, k, 0)]
        return focal_spot + jnp.where(known, d, jnp.zeros_like(d))
