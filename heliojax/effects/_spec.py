"""The effect library's registry and model construction: a base model plus effects."""

from __future__ import annotations

import collections.abc
import typing

import jax.numpy as jnp
import numpy as np

from .._kinematics import AbstractKinematicModel
from .._limits import real_problem
from .._parameters import ModuleT as ModelT, ParameterView, reference_leaves, set_references
from ._base import AbstractEffect, EffectModel, add_effects
from ._environment import DEFAULT_LATITUDE_DEG, Clock, OffsetDrift, Refraction, Thermal, Wind
from ._mechanical import ActuatorGeometry, Backlash, EncoderWobble, GravitySag
from ._survey import SurveyHeliostat, SurveyTarget

EFFECT_CLASSES: dict[str, type[AbstractEffect]] = {
    cls.NAME: cls
    for cls in (
        ActuatorGeometry,
        Backlash,
        Thermal,
        Wind,
        Clock,
        GravitySag,
        EncoderWobble,
        Refraction,
        SurveyHeliostat,
        SurveyTarget,
        OffsetDrift,
    )
}

EFFECT_NAMES: tuple[str, ...] = tuple(EFFECT_CLASSES)
"""The fixed list of effect names (the names discovery reports)."""


def effect_class(name: str) -> type[AbstractEffect]:
    """The effect class of ``name`` (ValueError for an unknown name, TypeError for one
    that is no string)."""
    if not isinstance(name, str):  # a list had failed as "unhashable type"
        got = f"{type(name).__name__} {name!r}"[:200]
        raise TypeError(f"effect name must be a string (one of {EFFECT_NAMES}), got {got}")
    try:
        return EFFECT_CLASSES[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; expected one of {EFFECT_NAMES}") from None


def with_effects(model: AbstractKinematicModel, effects: collections.abc.Sequence[str] | str) -> EffectModel:
    """``model`` wrapped by the named effects at their no-effect values (parameters 0,
    references at their defaults: set them from data with :func:`with_data_references`).

    Args:
        model: any kinematic model (a base model or a wrapper).
        effects: names from :data:`EFFECT_NAMES` (each at most once); one name alone
            is one effect (``"thermal"`` had been read as its letters: "unknown effect 't'").

    Raises:
        TypeError: ``model`` not a kinematic model, ``effects`` not names (strings).
        ValueError: an unknown or repeated name.
    """
    if not isinstance(model, AbstractKinematicModel):  # None had failed in a concatenation
        raise TypeError(f"with_effects: model must be a kinematic model, got {type(model).__name__}")
    names = (
        [effects]
        if isinstance(effects, str)
        else list(effects)
        if isinstance(effects, collections.abc.Iterable)
        else None
    )
    if names is None or not all(isinstance(e, str) for e in names):
        raise TypeError(f"with_effects: effects must be effect names (strings), got {effects!r}")
    dtype = jnp.asarray(ParameterView.of(model).to_vector(model)).dtype
    return add_effects(model, [effect_class(e).nominal(model, dtype) for e in names])


def data_references(fleet: typing.Any, mask: typing.Any = None) -> dict[str, float]:
    """Data-derived reference values: the mean known temperature (deg C), the
    mean record time (unix s; of the clock and the offset drift) over the valid records, and the plant latitude
    (deg, from ``fleet.origin_lla`` when the input has one)."""
    ctx = fleet.context
    m = np.asarray(fleet.mask if mask is None else mask, bool)
    refs = {}
    temp = np.asarray(ctx.temperature)[m]
    temp = temp[np.isfinite(temp)]
    refs["thermal_reference_c"] = float(temp.mean()) if temp.size else 20.0
    t = np.asarray(ctx.unix_time)[m]
    t = t[np.isfinite(t)]
    refs["clock_reference_s"] = float(np.round(t.mean())) if t.size else 1.65e9
    refs["offset_drift_reference_s"] = refs["clock_reference_s"]
    origin = getattr(fleet, "origin_lla", None)
    refs["clock_latitude_deg"] = float(np.asarray(origin)[0]) if origin is not None else DEFAULT_LATITUDE_DEG
    return refs


def with_data_references(model: ModelT, fleet: typing.Any, mask: typing.Any = None) -> ModelT:
    """``model`` with its effects' references set from ``fleet`` (:func:`data_references`)."""
    names = {leaf.name for leaf in reference_leaves(model)}
    if not names:
        return model
    return set_references(model, {k: v for k, v in data_references(fleet, mask).items() if k in names})


def make_effect(name: str, inner: AbstractKinematicModel | None = None, **values: float) -> AbstractEffect:
    """An effect for a model wrapping ``inner`` (None: a linear-law base such as the
    Stone model) from named parameter / reference values (others at their
    no-effect values / defaults), e.g. ``make_effect("backlash", backlash_1=3e-4)``.

    Raises:
        ValueError: an unknown effect or value name, or a value that is no finite real
            number (a NaN or inf magnitude had made every prediction of the effect NaN;
            a string had failed in ``float`` without its name).
    """
    for key, value in values.items():
        problem = real_problem(value)
        if problem is not None:
            raise ValueError(f"make_effect({name!r}): {key} {problem}")
    effect = effect_class(name).nominal(inner, jnp.float64)
    view = ParameterView.of(effect)
    refs = {leaf.name for leaf in reference_leaves(effect)}
    unknown = set(values) - set(view.names) - refs
    if unknown:
        raise ValueError(
            f"{name}: unknown values {sorted(unknown)}; parameters {view.names}, references {sorted(refs)}"
        )
    vec = view.to_vector(effect)
    vec = jnp.asarray([float(values.get(n, float(v))) for n, v in zip(view.names, np.asarray(vec))], jnp.float64)
    effect = view.from_vector(effect, vec)
    return set_references(effect, {k: float(v) for k, v in values.items() if k in refs})
