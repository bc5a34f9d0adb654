"""Hidden-effect suites: simulated fleets with known effects (tests, benchmark, notebook).

The simulator's injection point is the true model: each heliostat's true base
model (random Stone or actuator-model errors) is wrapped by the hidden effects
(:class:`heliojax.effects.EffectModel`) and :func:`heliojax.simulate_records`
turns the plant controller's counts into measured focal spots with it. The
approach directions that backlash needs come from the chronological order of
each heliostat's counts (:func:`heliojax.approach_directions`), as the data
loader derives them.
"""

from __future__ import annotations

import collections.abc

import equinox as eqx
import jax
import jax.numpy as jnp

from .._kinematics import ActuatorModel, StoneModel, inverse_aim
from .._simulate import (
    _check_sizes,  # pyright: ignore[reportPrivateUsage]
    approach_directions,
    calibration_target,
    check_magnitudes,
    random_stone_models,
    simulate_records,
    synthetic_contexts,
    synthetic_geometry,
)
from ..effects import AbstractEffect, EffectModel


@eqx.filter_jit
def random_actuator_models(key, n: int, angle_sigma: float = 3e-3, dtype=jnp.float64) -> ActuatorModel:
    """``n`` true actuator models: tilts ~ N(0, angle_sigma) rad, angle offsets
    ~ N(0, 3 angle_sigma) rad, increment scales ~ N(0, 2e-3), stroke offsets 0.

    Raises:
        ValueError: ``n`` no whole number >= 1 (0 had given models of no heliostat), or
            ``angle_sigma`` not a finite number >= 0 (a NaN had made every model NaN).
    """
    _check_sizes("random_actuator_models", n=n)
    check_magnitudes("random_actuator_models", angle_sigma=angle_sigma)
    ks = jax.random.split(key, 4)
    tilts = angle_sigma * jax.random.normal(ks[0], (4, n), dtype)
    off = 3 * angle_sigma * jax.random.normal(ks[1], (n, 2), dtype)
    inc = 2e-3 * jax.random.normal(ks[2], (n, 2), dtype)
    return ActuatorModel(
        alpha=tilts[0],
        beta=tilts[1],
        gamma=tilts[2],
        delta=tilts[3],
        angle_offset=off,
        increment_scale=inc,
        stroke_offset=jnp.zeros((n, 2), dtype),
    )


@eqx.filter_jit
def _controller_counts(geometry, sun, target):
    def one(g, s):
        c = jnp.round(inverse_aim(StoneModel.nominal(s.dtype), g, target.centre, s))
        return jnp.clip(c, g.actuators.min_counts, g.actuators.max_counts)

    return jax.vmap(lambda g, ss: jax.vmap(lambda s: one(g, s))(ss))(geometry, sun)


def _broadcast(effect, n: int):
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x)), effect)


def simulate_fleet(
    seed: int,
    n_heliostats: int = 20,
    n_records: int = 60,
    *,
    effects: collections.abc.Sequence = (),
    per_heliostat_effects: collections.abc.Sequence = (),
    base: str = "stone8",
    noise_mrad: float = 0.25,
    weather: bool = True,
):
    """A simulated fleet with hidden effects, as a :class:`heliojax.Fleet`.

    Args:
        seed: PRNG seed (geometry, true models, times, weather, noise).
        n_heliostats, n_records: fleet size.
        effects: effects common to all heliostats (unbatched
            :class:`~heliojax.effects.AbstractEffect` instances).
        per_heliostat_effects: effects batched over the heliostats (leading axis).
        base: ``"stone8"`` (true Stone models, linear counts map) or
            ``"actuator"`` (true actuator models).
        noise_mrad: measurement noise per tangent-plane component, mrad.
        weather: synthetic temperature and wind (else NaN).

    Returns:
        ``(fleet, truth)`` with ``truth`` the batched true model.

    Raises:
        ValueError: ``base`` neither name (another had simulated actuator models without
            a word), an effect that is no :class:`~heliojax.effects.AbstractEffect` (an
            effect's name had failed deep inside JAX's ``asarray``) or, among
            ``per_heliostat_effects``, one not batched over the ``n_heliostats``.
    """
    if base not in ("stone8", "actuator"):
        raise ValueError(f"simulate_fleet: base must be 'stone8' or 'actuator', got {base!r}"[:200])
    for name, group in (("effects", effects), ("per_heliostat_effects", per_heliostat_effects)):
        items = [group] if isinstance(group, str | AbstractEffect) else list(group)
        wrong = [e for e in items if not isinstance(e, AbstractEffect)]
        if isinstance(group, str | AbstractEffect) or wrong:
            got = f"{type(group).__name__}" if isinstance(group, str | AbstractEffect) else f"{wrong[0]!r}"
            raise ValueError(
                f"simulate_fleet: {name} must be a sequence of effect instances (heliojax.effects.make_effect("
                f"name, ...)), got {got}"[:300]
            )
    for effect in per_heliostat_effects:
        sizes = {jnp.shape(x)[:1] for x in jax.tree.leaves(effect) if eqx.is_array(x)}
        if sizes - {(n_heliostats,)}:
            raise ValueError(
                f"simulate_fleet: per_heliostat_effects: {type(effect).__name__} has arrays of leading shape "
                f"{sorted(sizes - {(n_heliostats,)})}; expected ({n_heliostats},), one row per heliostat "
                "(effects common to all go in effects)"
            )
    key = jax.random.PRNGKey(seed)
    k_geo, k_model, k_ctx, k_noise = jax.random.split(key, 4)
    h, m = n_heliostats, n_records
    geometry = synthetic_geometry(k_geo, h)
    base_models = random_stone_models(k_model, h) if base == "stone8" else random_actuator_models(k_model, h)
    context = synthetic_contexts(k_ctx, h, m, weather=weather)
    target = calibration_target()
    counts = _controller_counts(geometry, context.sun, target)
    context = eqx.tree_at(lambda c: c.approach, context, approach_directions(counts))
    all_effects = tuple(_broadcast(e, h) for e in effects) + tuple(per_heliostat_effects)
    truth = EffectModel(base_models, all_effects) if all_effects else base_models
    fleet = simulate_records(k_noise, truth, geometry, context, target, noise_mrad=noise_mrad)
    # every record is kept, also a spot beside the 6 x 7 m target: the target is the
    # plane extended to hold every spot (no spot is off it, :func:`heliojax.spots_off_target`)
    uv = jnp.abs(target.to_plane(fleet.focal_spot))
    wide = eqx.tree_at(
        lambda t: (t.half_width, t.half_height),
        fleet.targets,
        (
            jnp.maximum(fleet.targets.half_width, jnp.nanmax(uv[..., 0])),
            jnp.maximum(fleet.targets.half_height, jnp.nanmax(uv[..., 1])),
        ),
    )
    fleet = eqx.tree_at(lambda f: (f.mask, f.targets), fleet, (jnp.ones((h, m), bool), wide))
    return fleet, truth
