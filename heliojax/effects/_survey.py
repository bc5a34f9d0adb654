"""Survey errors: the heliostat's or the target's surveyed position is off."""

from __future__ import annotations

import typing

import equinox as eqx
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


@typing.final
class SurveyTarget(AbstractEffect):
    """Survey error of the calibration target.

    Physical meaning: the target (and so every focal spot measured on it) is
    at ``+ d`` (ENU m) from where the data place it. Correction: the focal spot
    the model compares with is the recorded one moved by ``d``.

    Parameters: ``survey_target_e``, ``_n``, ``_u`` (m); physically one value
    for all heliostats that use the target.
    Driving input: none. Residual signature: a fixed displacement on the
    target, i.e. a beam error of ``d_perp / distance`` in a direction fixed per
    heliostat - largely absorbed by each heliostat's tilts.
    """

    delta: Float[Array, "*h 3"] = parameter(
        unit="m", scale=0.1, typical=0.05, name="survey_target", shape=(3,), suffixes=("e", "n", "u")
    )

    NAME: typing.ClassVar[str] = "survey_target"
    DRIVERS: typing.ClassVar[tuple[str, ...]] = ()

    @classmethod
    def nominal(cls, inner, dtype=None):
        return cls(delta=zeros(dtype, 3))

    def adjust_focal(self, focal_spot, context):
        return focal_spot + self.delta
