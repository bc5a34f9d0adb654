"""Composing model specifications: a base :class:`~heliojax.ModelSpec` plus effects."""

from __future__ import annotations

import dataclasses
import typing

import jax.numpy as jnp
import numpy as np

from .._calibration import ModelSpec, model_spec
from ._base import AbstractEffect, EffectModel
from ._environment import Clock, Refraction, Thermal, Wind
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
    )
}

EFFECT_NAMES: tuple[str, ...] = tuple(EFFECT_CLASSES)
"""The fixed list of effect names (the names discovery reports)."""


def effect_class(name: str) -> type[AbstractEffect]:
    """The effect class of ``name`` (ValueError for an unknown name)."""
    try:
        return EFFECT_CLASSES[name]
    except KeyError:
        raise ValueError(f"unknown effect {name!r}; expected one of {EFFECT_NAMES}") from None


def base_kind_of(spec: ModelSpec) -> str:
    """``"stone8"`` or ``"actuator"`` of a (possibly effect-extended) spec."""
    return spec.kind.split("+")[0]


@dataclasses.dataclass(frozen=True)
class EffectLayout:
    """Where each effect's parameters and references sit in the vector (static)."""

    effect: str
    params: tuple[int, ...]
    references: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class EffectSpecBuilder:
    """Hashable builder ``p -> EffectModel(base, effects)`` of :func:`with_effects`."""

    base_builder: typing.Callable
    base_kind: str
    n_base: int
    layout: tuple[EffectLayout, ...]

    def __call__(self, p):
        p = jnp.asarray(p)
        base = self.base_builder(p[: self.n_base])
        effects = []
        for lay in self.layout:
            cls = EFFECT_CLASSES[lay.effect]
            params = p[jnp.asarray(lay.params, dtype=jnp.int32)] if lay.params else p[:0]
            refs = tuple(p[i] for i in lay.references)
            effects.append(cls.from_vector(params, refs or cls.reference_defaults(), base_kind=self.base_kind))
        return EffectModel(base, tuple(effects))


def with_effects(
    base: ModelSpec | str, effects: typing.Sequence[str], *, free_effects: bool = True
) -> ModelSpec:
    """A :class:`~heliojax.ModelSpec` of ``base`` extended by ``effects``.

    The vector is the base's, then each effect's fitted parameters
    (:meth:`AbstractEffect.param_names`, nominal 0 = no effect), then each
    effect's references (data-derived constants, never free; fill them with
    :func:`effect_initial`). ``kind`` is ``"<base>+<effect>+..."``.

    Args:
        base: ``"stone8"``, ``"actuator"`` or a base spec.
        effects: effect names from :data:`EFFECT_NAMES` (each at most once).
        free_effects: whether the effects' parameters are fitted.
    """
    spec = model_spec(base) if isinstance(base, str) else base
    if isinstance(spec.builder, EffectSpecBuilder):
        raise ValueError("with_effects: give the base spec, not one that already has effects")
    effects = tuple(effects)
    if len(set(effects)) != len(effects):
        raise ValueError(f"with_effects: repeated effect in {effects}")
    kind = base_kind_of(spec)
    names = list(spec.names)
    scales = list(spec.scales)
    units = list(spec.units)
    nominal = list(spec.nominal)
    free = list(spec.free)
    layout = []
    for e in effects:
        cls = effect_class(e)
        pn = cls.param_names(kind)
        p_idx = tuple(range(len(names), len(names) + len(pn)))
        names += list(pn)
        scales += list(cls.param_scales(kind))
        units += list(cls.param_units(kind))
        nominal += [0.0] * len(pn)
        if free_effects:
            free += list(pn)
        layout.append((e, p_idx))
    full_layout = []
    for e, p_idx in layout:
        cls = effect_class(e)
        r_idx = tuple(range(len(names), len(names) + len(cls.REFERENCE_NAMES)))
        names += list(cls.REFERENCE_NAMES)
        scales += [1.0] * len(cls.REFERENCE_NAMES)
        units += ["ref"] * len(cls.REFERENCE_NAMES)
        nominal += list(cls.reference_defaults())
        full_layout.append(EffectLayout(e, p_idx, r_idx))
    return ModelSpec(
        kind="+".join((kind,) + effects),
        names=tuple(names),
        scales=tuple(float(s) for s in scales),
        free=tuple(free),
        units=tuple(units),
        nominal=tuple(float(v) for v in nominal),
        builder=EffectSpecBuilder(spec.builder, kind, len(spec.names), tuple(full_layout)),
    )


def data_references(fleet_or_data, mask=None) -> dict[str, float]:
    """Data-derived reference values: the mean known temperature (deg C), the
    mean record time (unix s) over the valid records, and the plant latitude
    (deg, from ``fleet.origin_lla`` when the input has one)."""
    ctx = fleet_or_data.context
    m = np.asarray(fleet_or_data.mask if mask is None else mask, bool)
    refs = {}
    temp = np.asarray(ctx.temperature)[m]
    temp = temp[np.isfinite(temp)]
    refs["thermal_reference_c"] = float(temp.mean()) if temp.size else Thermal.reference_defaults()[0]
    t = np.asarray(ctx.unix_time)[m]
    t = t[np.isfinite(t)]
    refs["clock_reference_s"] = float(np.round(t.mean())) if t.size else Clock.reference_defaults()[0]
    origin = getattr(fleet_or_data, "origin_lla", None)
    refs["clock_latitude_deg"] = float(np.asarray(origin)[0]) if origin is not None else Clock.reference_defaults()[1]
    return refs


def effect_initial(spec: ModelSpec, fleet_or_data, mask=None, dtype=jnp.float64):
    """``(H, P)`` start values of ``spec`` for :func:`heliojax.fit_fleet`: nominal
    parameters and the references from :func:`data_references`."""
    refs = data_references(fleet_or_data, mask)
    vec = np.array(spec.nominal, dtype=np.float64)
    for i, n in enumerate(spec.names):
        if n in refs:
            vec[i] = refs[n]
    h = np.shape(fleet_or_data.mask)[0]
    return jnp.asarray(np.broadcast_to(vec, (h, vec.size)), dtype)


def make_effect(name: str, base_kind: str = "stone8", **values) -> AbstractEffect:
    """An effect from named parameter / reference values (others 0 / default),
    e.g. ``make_effect("backlash", backlash_1=3e-4)``."""
    cls = effect_class(name)
    pn = cls.param_names(base_kind)
    unknown = set(values) - set(pn) - set(cls.REFERENCE_NAMES)
    if unknown:
        raise ValueError(f"{name}: unknown values {sorted(unknown)}; parameters {pn}, references {cls.REFERENCE_NAMES}")
    p = jnp.asarray([float(values.get(n, 0.0)) for n in pn], jnp.float64)
    refs = tuple(float(values.get(n, d)) for n, d in zip(cls.REFERENCE_NAMES, cls.reference_defaults()))
    return cls.from_vector(p, refs, base_kind=base_kind)
