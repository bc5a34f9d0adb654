"""Evaluation of (fitted) models on a fleet's records, and the start geometry."""

from __future__ import annotations

import functools
import typing

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._aim import direction_jacobian_mrad
from .._heliostat import HeliostatGeometry, RecordContext
from .._kinematics import AbstractKinematicModel
from .._parameters import ParameterView, and_masks, on_host
from .._programs import cached_jit
from ._batching import AbstractBatching
from ._fit import batched_for, check_fleet, fit_mask
from ._records import sanitise


@functools.partial(cached_jit, quick=True)
def _errors_program(models, geometry, counts, context, focal, mask):
    """``(beam errors (H, M), residual components (H, M, 2))`` in mrad, NaN outside
    ``mask``: one program for both, so that a run compiles and loads it once."""

    def per_heliostat(model, g, c, x, f, m):
        c2, x2, f2, use, _ = sanitise(g, c, x, f, m)

        def one(ci, xi, fi):
            return model.beam_error(g, ci, xi, fi), model.beam_components(g, ci, xi, fi)

        e, r = jax.vmap(one)(c2, x2, f2)
        return jnp.where(use, e * 1e3, jnp.nan), jnp.where(use[:, None], r * 1e3, jnp.nan)

    return jax.vmap(per_heliostat)(models, geometry, counts, context, focal, mask)


def beam_errors_mrad(
    models: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    counts: Float[Array, "H M 2"],
    context: RecordContext,
    focal: Float[Array, "H M 3"],
    mask: Bool[Array, "H M"],
) -> Float[Array, "H M"]:
    """Beam pointing error (mrad) of every record ``(H, M)`` under models batched
    along ``H``; NaN where ``mask`` is False or an input is not finite."""
    return _errors_program(models, geometry, counts, context, focal, mask)[0]


def residuals_mrad(
    models: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    counts: Float[Array, "H M 2"],
    context: RecordContext,
    focal: Float[Array, "H M 3"],
    mask: Bool[Array, "H M"],
) -> Float[Array, "H M 2"]:
    """Tangent-plane residual components (mrad) of every record; NaN outside ``mask``."""
    return _errors_program(models, geometry, counts, context, focal, mask)[1]


@functools.partial(cached_jit, quick=True)
def _jacobian_program(view, models, geometry, counts, context, focal, mask):
    def one(model, g, c, x, f, m):
        c, x, f, use, _ = sanitise(g, c, x, f, m)
        jac = jax.vmap(lambda ci, xi, fi: direction_jacobian_mrad(view, model, g, ci, xi, fi))(c, x, f)
        return jnp.where(use[:, None, None], jac, 0.0)

    return jax.vmap(one)(models, geometry, counts, context, focal, mask)


def residual_jacobians(
    models: AbstractKinematicModel,
    view: ParameterView,
    geometry: HeliostatGeometry,
    counts: Float[Array, "H M 2"],
    context: RecordContext,
    focal: Float[Array, "H M 3"],
    mask: Bool[Array, "H M"],
) -> Float[Array, "H M 2 F"]:
    """Jacobian of each record's two residual components (mrad, as
    :func:`residuals_mrad`) w.r.t. the free parameters of ``view`` (physical units,
    :attr:`ParameterView.free_index` order) of the batched ``models``; zero rows
    outside ``mask`` and for records that are not finite. One program per shape:
    the change-point scan, the pointing drift and calibration planning share it."""
    return _jacobian_program(view, models, geometry, counts, context, focal, mask)


def _fleet_arguments(models: AbstractKinematicModel, fleet: typing.Any, mask: typing.Any, who: str):
    """``(models batched over the fleet, the records to use)``, checked as :func:`heliojax.fit`
    checks them: models batched for another fleet size had failed in a vmap naming JAX's
    argument names, a mask of another shape in NumPy's broadcasting."""
    check_fleet(fleet, who=who)
    shape = tuple(np.shape(fleet.mask))
    mask = fit_mask(mask, shape, who)
    return batched_for(models, shape[0], who, "models"), (fleet.mask if mask is None else and_masks(mask, fleet.mask))


def fleet_beam_errors_mrad(
    models: AbstractKinematicModel, fleet: typing.Any, mask: Bool[Array, "H M"] | None = None
) -> Float[Array, "H M"]:
    """Per-record beam error (mrad) of ``models`` (one model, or batched over the
    fleet's heliostats, e.g. ``solution.model``) on ``fleet``; NaN outside ``mask``."""
    models, m = _fleet_arguments(models, fleet, mask, "fleet_beam_errors_mrad")
    return beam_errors_mrad(models, fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, m)


def fleet_residuals_mrad(
    models: AbstractKinematicModel,
    fleet: typing.Any,
    mask: Bool[Array, "H M"] | None = None,
    *,
    batching: AbstractBatching | None = None,
) -> Float[Array, "H M 2"]:
    """Per-record residual components (mrad) of ``models`` on ``fleet``; NaN outside
    ``mask``. With ``batching`` (e.g. a fit's :class:`heliojax.Threaded`), the
    program runs by its :meth:`~heliojax.fitting.AbstractBatching.run` (in blocks of
    heliostats on the block threads); the values are the same."""
    models, m = _fleet_arguments(models, fleet, mask, "fleet_residuals_mrad")
    lanes = (models, fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, m)
    if batching is None:
        return residuals_mrad(*lanes)
    return batching.run(_errors_program, (), lanes)[1]


def row_median(e: ArrayLike, empty: float = np.inf) -> np.ndarray:
    """``(H,)`` median of each row of ``e`` (``(H, M)``) over its finite values;
    ``empty`` for a row without one. One sort of the whole array: ``np.nanmedian``
    over rows is several times slower on a fleet's padded records."""
    e = np.asarray(e, float)
    finite = np.isfinite(e)
    s = np.sort(np.where(finite, e, np.inf), axis=1)
    n = finite.sum(axis=1)
    rows = np.arange(e.shape[0])
    if e.shape[1] == 0:
        return np.full(e.shape[0], empty)
    med = 0.5 * (s[rows, np.clip((n - 1) // 2, 0, None)] + s[rows, np.clip(n // 2, 0, None)])
    return np.where(n > 0, med, empty)


def typical_actuators(geometry: HeliostatGeometry, valid: Bool[ArrayLike, " H"]) -> typing.Any:
    """Median actuator values over the ``valid`` heliostats (the start geometry for
    heliostats whose nominal properties are far off, e.g. PAINT's BF41)."""
    valid_np = np.asarray(valid)
    return jax.tree.map(lambda x: jnp.asarray(np.median(np.asarray(x)[valid_np], axis=0), x.dtype), geometry.actuators)


def choose_start_geometry(
    fleet: typing.Any, model: AbstractKinematicModel, mask: Bool[Array, "H M"] | None = None
) -> tuple[HeliostatGeometry, np.ndarray, np.ndarray]:
    """Per heliostat, the better start of two: its own nominal geometry, or its
    geometry with the fleet's typical (median) actuator values.

    The typical values are the median over the heliostats whose own records
    (``mask``, default all valid ones) give a finite uncalibrated error under the
    nominal ``model`` - heliostats without usable records or with broken inputs
    never move it. The choice is by the uncalibrated median beam error of the
    heliostat's own records, so no threshold is involved.

    Returns:
        ``(geometry, replaced, sources)``: the start geometry, ``replaced`` bool
        ``(H,)`` (started from the typical actuators) and ``sources`` bool ``(H,)``
        (the heliostats the typical actuators came from).
    """
    models, m = _fleet_arguments(model, fleet, mask, "choose_start_geometry")
    h = int(np.shape(fleet.mask)[0])
    e_own = beam_errors_mrad(models, fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, m)
    own = row_median(e_own)
    sources = np.any(np.asarray(m), axis=1) & np.isfinite(own)
    if not sources.any():
        return fleet.geometry, np.zeros(h, bool), sources
    alt = _with_actuators(fleet.geometry, typical_actuators(fleet.geometry, sources))
    e_alt = beam_errors_mrad(models, alt, fleet.counts, fleet.context, fleet.focal_spot, m)
    replaced = np.isfinite(row_median(e_alt)) & (row_median(e_alt) < own)
    return select_geometry(replaced, alt, fleet.geometry), replaced, sources


def select_geometry(take: np.ndarray, a: HeliostatGeometry, b: HeliostatGeometry) -> HeliostatGeometry:
    """Per heliostat, geometry ``a`` where ``take`` ``(H,)`` else ``b`` (both batched)."""
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    if on_host(*la, *lb) and all(x.dtype == y.dtype for x, y in zip(la, lb, strict=True)):
        # a per-heliostat select of concrete arrays: on the host, no program to load
        return jax.tree.map(
            lambda x, y: jax.device_put(
                np.where(np.reshape(take, (-1,) + (1,) * (np.ndim(x) - 1)), np.asarray(x), np.asarray(y))
            ),
            a,
            b,
        )
    return _select_geometry(jax.device_put(np.asarray(take, bool)), a, b)


@functools.partial(cached_jit, quick=True)
def _with_actuators(geometry: HeliostatGeometry, typical: typing.Any) -> HeliostatGeometry:
    """``geometry`` (batched ``H``) with every heliostat's actuators set to ``typical``."""
    actuators = jax.tree.map(lambda t, x: jnp.broadcast_to(t, x.shape), typical, geometry.actuators)
    return HeliostatGeometry.build(
        geometry.position,
        actuators,
        geometry.joint_translation_1,
        geometry.joint_translation_2,
        geometry.concentrator_translation,
    )


@functools.partial(cached_jit, quick=True)
def _select_geometry(take: Bool[Array, " H"], a: HeliostatGeometry, b: HeliostatGeometry) -> HeliostatGeometry:
    """Per heliostat, ``a`` where ``take`` else ``b``."""
    return jax.tree.map(lambda x, y: jnp.where(take.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b)


__all__ = [
    "beam_errors_mrad",
    "choose_start_geometry",
    "fleet_beam_errors_mrad",
    "fleet_residuals_mrad",
    "residual_jacobians",
    "residuals_mrad",
    "typical_actuators",
]
