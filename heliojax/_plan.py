"""Planning calibration measurements: which instants to measure next, and which
heliostats most need measuring.

Criterion (I-optimal design): a camera-target measurement of a heliostat adds
the information ``J^T J / sigma^2`` of its two residual components (``J``: their
Jacobian w.r.t. the free parameters at that instant, ``sigma``: the noise per
component) to the current parameter covariance ``C``. What the plant cares
about is the pointing error in operation, so the objective is the expected
squared beam error over the heliostat's *operating envelope* (sun positions of
a year, weighted by DNI, aiming at the receiver)::

    U(C) = sum_e w_e tr(J_e C J_e^T) = tr(C M),   M = sum_e w_e J_e^T J_e

the integrated prediction variance. It is in mrad^2, directly the quantity an
operator reads, and unlike D-optimality it does not spend measurements on
parameter combinations that never matter for aiming. Measurements are chosen
greedily, each maximising the drop of ``U`` given those already chosen (the
drop of a rank-2 update has a closed form, so every candidate of every
heliostat is scored at once)::

    C' = C - C J^T S^-1 J C,   S = sigma^2 I + J C J^T,   U(C) - U(C') = tr(S^-1 J C M C J^T)

Greedy selection for this (submodular-like) criterion is the standard
sequential design; it is exact for one measurement.
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._heliostat import HeliostatGeometry, RecordContext
from ._kinematics import AbstractKinematicModel
from ._parameters import ParameterView
from .fitting import sanitise


def residual_jacobians(
    models: AbstractKinematicModel,
    view: ParameterView,
    geometry: HeliostatGeometry,
    counts: Float[Array, "H K 2"],
    context: RecordContext,
    spots: Float[Array, "H K 3"],
    mask: Bool[Array, "H K"],
) -> Float[Array, "H K 2 F"]:
    """Jacobian of each record's two residual components (mrad) w.r.t. the free
    parameters (physical units, :attr:`ParameterView.free_index` order); zero rows
    outside ``mask``."""

    @eqx.filter_jit
    def program(models, geometry, counts, context, spots, mask):
        def one(model, g, c, x, f, m):
            c, x, f, use, _ = sanitise(g, c, x, f, m)
            p0 = view.to_vector(model)
            idx = jnp.asarray(view.free_index, dtype=jnp.int32)

            def comp(q, ci, xi, fi):
                return view.from_vector(model, p0.at[idx].set(q)).beam_components(g, ci, xi, fi) * 1e3

            jac = jax.vmap(lambda ci, xi, fi: jax.jacfwd(comp)(p0[idx], ci, xi, fi))(c, x, f)
            return jnp.where(use[:, None, None], jac, 0.0)

        return jax.vmap(one)(models, geometry, counts, context, spots, mask)

    return program(models, geometry, counts, context, spots, mask)


def envelope_matrix(jac: Float[Array, "H E 2 F"], weight: Float[Array, "*h E"]) -> Float[Array, "H F F"]:
    """``M = sum_e w_e J_e^T J_e`` with weights normalised to sum 1 per heliostat."""
    w = jnp.broadcast_to(jnp.asarray(weight, jac.dtype), jac.shape[:2])
    w = w / jnp.maximum(jnp.sum(w, axis=1, keepdims=True), 1e-300)
    return jnp.einsum("he,heif,heig->hfg", w, jac, jac)


@typing.final
class MeasurementPlan(eqx.Module):
    """Greedy I-optimal choice of ``K`` measurements per heliostat.

    Attributes:
        chosen: ``(H, K)`` candidate indices in the order chosen (-1 where fewer
            valid candidates than ``K``).
        uncertainty_before_mrad: ``(H,)`` ``sqrt(U)``: RMS predicted pointing error
            over the envelope from parameter uncertainty, before.
        uncertainty_after_mrad: ``(H, K)`` the same after each chosen measurement.
        covariance_after: ``(H, F, F)`` the predicted covariance after all of them.
    """

    chosen: Int[Array, "H K"]
    uncertainty_before_mrad: Float[Array, " H"]
    uncertainty_after_mrad: Float[Array, "H K"]
    covariance_after: Float[Array, "H F F"]


@eqx.filter_jit
def _greedy(cov, cand_jac, cand_valid, m_env, noise, budget: int):
    def one(c, jac, valid, m, sigma):
        eye = jnp.eye(2, dtype=c.dtype)

        def gains(c):
            a = jnp.einsum("kif,fg->kig", jac, c)  # J C
            s = sigma**2 * eye + jnp.einsum("kif,kjf->kij", a, jac)
            g = jnp.einsum("kif,fg,kjg->kij", a, m, a)
            return jnp.trace(jnp.linalg.solve(s, g), axis1=1, axis2=2), a, s

        def step(carry, _):
            c, avail = carry
            gain, a, s = gains(c)
            gain = jnp.where(avail, gain, -jnp.inf)
            k = jnp.argmax(gain)
            ok = avail[k]
            ak, sk = a[k], s[k]
            c_new = c - ak.T @ jnp.linalg.solve(sk, ak)
            c_new = 0.5 * (c_new + c_new.T)
            c = jnp.where(ok, c_new, c)
            avail = avail.at[k].set(False)
            return (c, avail), (jnp.where(ok, k, -1), jnp.sqrt(jnp.maximum(jnp.trace(c @ m), 0.0)))

        u0 = jnp.sqrt(jnp.maximum(jnp.trace(c @ m), 0.0))
        (c_end, _), (chosen, u) = jax.lax.scan(step, (c, valid), None, length=budget)
        return chosen, u0, u, c_end

    return jax.vmap(one)(cov, cand_jac, cand_valid, m_env, noise)


def plan_measurements(
    covariance: Float[Array, "H F F"],
    candidate_jacobians: Float[Array, "H K 2 F"],
    candidate_valid: Bool[Array, "H K"],
    envelope: Float[Array, "H F F"],
    noise_mrad: Float[Array, "*h"],
    budget: int,
) -> MeasurementPlan:
    """Choose ``budget`` measurements per heliostat among its candidates.

    Args:
        covariance: current parameter covariance (physical units of the free
            parameters): a fit's posterior, or a prior's ``diag(sigma^2)``.
        candidate_jacobians: from :func:`residual_jacobians` at each candidate.
        candidate_valid: which candidates may be chosen.
        envelope: ``M`` of :func:`envelope_matrix`.
        noise_mrad: measurement noise per residual component, scalar or ``(H,)``.
        budget: measurements per heliostat (static).
    """
    h = covariance.shape[0]
    noise = jnp.broadcast_to(jnp.asarray(noise_mrad, covariance.dtype), (h,))
    chosen, u0, u, c_end = _greedy(
        covariance, candidate_jacobians, jnp.asarray(candidate_valid, bool), envelope, noise, int(budget)
    )
    return MeasurementPlan(chosen=chosen, uncertainty_before_mrad=u0, uncertainty_after_mrad=u, covariance_after=c_end)


def predicted_uncertainty_mrad(
    covariance: Float[Array, "H F F"], envelope: Float[Array, "H F F"]
) -> Float[Array, " H"]:
    """``sqrt(tr(C M))``: RMS predicted pointing error over the envelope (mrad)
    from parameter uncertainty; rank heliostats by it to see which most need measuring."""
    return jnp.sqrt(jnp.maximum(jnp.einsum("hfg,hgf->h", covariance, envelope), 0.0))


__all__ = [
    "MeasurementPlan",
    "envelope_matrix",
    "plan_measurements",
    "predicted_uncertainty_mrad",
    "residual_jacobians",
]
