"""Record-level helpers shared by every fit and evaluation: masking and sanitising."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._heliostat import HeliostatGeometry, RecordContext
from .._kinematics import AbstractKinematicModel


def finite_records(
    counts: Float[Array, "M 2"], context: RecordContext, focal: Float[Array, "M 3"]
) -> Bool[Array, " M"]:
    """Records whose counts, sun and focal spot are all finite."""
    return jnp.all(jnp.isfinite(counts), -1) & jnp.all(jnp.isfinite(context.sun), -1) & jnp.all(jnp.isfinite(focal), -1)


def sanitise(
    geometry: HeliostatGeometry,
    counts: Float[Array, "M 2"],
    context: RecordContext,
    focal: Float[Array, "M 3"],
    mask: Bool[Array, " M"],
) -> tuple[Float[Array, "M 2"], RecordContext, Float[Array, "M 3"], Bool[Array, " M"], Bool[Array, ""]]:
    """Replace masked or non-finite records of one heliostat by a harmless dummy
    (mid-range counts, sun in the south, spot 100 m south) so that no NaN reaches
    values or gradients. Weather of *used* records stays as it is (NaN = unknown;
    effects treat it).

    Returns:
        ``(counts, context, focal, use, bad_input)``: ``use`` marks the records to
        use, ``bad_input`` whether a masked-in record was not finite.
    """
    finite = finite_records(counts, context, focal)
    use = mask & finite
    act = geometry.actuators
    mid = 0.5 * (act.min_counts + act.max_counts)
    dtype = counts.dtype
    dummy_sun = jnp.asarray([0.0, -0.7071067811865476, 0.7071067811865476], dtype)
    dummy_focal = geometry.position + jnp.asarray([0.0, -100.0, 30.0], dtype)
    counts = jnp.where(use[:, None], counts, mid)
    focal = jnp.where(use[:, None], focal, dummy_focal)

    def fix(x):
        u = use.reshape(use.shape + (1,) * (x.ndim - 1))
        return jnp.where(u, x, jnp.zeros_like(x))

    context = jax.tree_util.tree_map(fix, context)
    context = eqx.tree_at(lambda c: c.sun, context, jnp.where(use[:, None], context.sun, dummy_sun))
    bad_input = jnp.any(mask & ~finite)
    return counts, context, focal, use, bad_input


def record_residuals_mrad(
    model: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    counts: Float[Array, "M 2"],
    context: RecordContext,
    focal: Float[Array, "M 3"],
) -> Float[Array, "M 2"]:
    """Tangent-plane beam error components (mrad) of one heliostat's records."""
    return jax.vmap(lambda c, x, f: model.beam_components(geometry, c, x, f))(counts, context, focal) * 1e3


__all__ = ["finite_records", "record_residuals_mrad", "sanitise"]
