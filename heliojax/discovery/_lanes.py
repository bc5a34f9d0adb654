"""Lanes: the fleet replicated once per cross-validation fold, and the compiled
fit / Jacobian programs that run over all lanes at once.

A *lane* is one heliostat under one record mask: lane ``(f, h)`` holds
heliostat ``h`` with the records of every fold but ``f`` (``f = 0``: all
records). Fitting all lanes at once gives the full-data fit and every
cross-validation fit in one call; lanes are grouped by their heliostat's record
width (:func:`lane_groups`), one compiled program per group, so that a heliostat
with few records does not run over the slots of the fleet's largest.

The fit is the same Levenberg-Marquardt problem as :func:`heliojax.fit`
(tangent-plane residuals in mrad, scaled parameters, masked records replaced
by :func:`heliojax.fitting.sanitise`, heliostats mapped by the same batching
strategies, solved by :func:`heliojax.fitting.solve_least_squares` with the same
cost ``0.5 * sum r^2``), over *one* model that carries the base parameters and
the parameters of every candidate effect (``layout.template``, an
:class:`heliojax.EffectModel`; vectors in its :class:`heliojax.ParameterView`
order). Which effect parameters move is dynamic data (solver columns ``sel``),
only the solver's width is static and bucketed, so every candidate, every fold
and every step of the discovery reuses a handful of compiled programs.
(``fit`` fixes the free set statically, which would recompile per candidate,
and counts every free parameter against a heliostat's records.)
"""

from __future__ import annotations

import dataclasses
import functools
import typing
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._beam import beam_error_components, reflected_ray
from .._geometry import normalize
from .._heliostat import chain_pose
from .._kinematics import AbstractKinematicModel
from .._parameters import ParameterView
from .._programs import cached_jit
from ..effects import EffectModel, OffsetStep, add_effects, with_data_references, with_effects
from ..fitting import (
    AbstractBatching,
    block_lanes,
    day_labels,
    default_batching,
    default_solver,
    record_rows,
    record_rows_and_jacobian,
    residual_with_jacobian,
    sanitise,
    solve_least_squares,
)

Records = tuple[typing.Any, typing.Any, typing.Any, typing.Any, typing.Any]
"""``(geometry, counts, context, focal_spot, mask)`` of a (lane-tiled) fleet."""


def fleet_records(fleet: typing.Any) -> Records:
    """The arrays of ``fleet`` the compiled programs take (no ids, no report)."""
    return (fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, fleet.mask)


@dataclasses.dataclass(frozen=True)
class Layout:
    """Static column layout of the discovery's universal model.

    Attributes:
        view: the :class:`heliojax.ParameterView` of base + all candidate effects.
        free_index: positions (in ``view.names``) of the columns the solver sees:
            the base's free parameters, then every effect's free parameters.
        base_cols: solver columns of the base's free parameters.
        effect_cols: effect name -> its solver columns.
        effect_param_names: effect name -> its parameter names.
        effect_typical: effect name -> typical sizes in scaled units.
        effect_units: effect name -> parameter units.
    """

    view: ParameterView
    free_index: tuple[int, ...]
    base_cols: tuple[int, ...]
    effect_cols: tuple[tuple[str, tuple[int, ...]], ...]
    effect_param_names: tuple[tuple[str, tuple[str, ...]], ...]
    effect_typical: tuple[tuple[str, tuple[float, ...]], ...] = ()
    effect_units: tuple[tuple[str, tuple[str, ...]], ...] = ()

    @property
    def n_free(self) -> int:
        return len(self.free_index)

    def cols(self, effect: str) -> tuple[int, ...]:
        return dict(self.effect_cols)[effect]

    def params(self, effect: str) -> tuple[str, ...]:
        return dict(self.effect_param_names)[effect]

    def units(self, effect: str) -> tuple[str, ...]:
        return dict(self.effect_units)[effect]

    def typical(self, effect: str) -> np.ndarray:
        """The effect's typical sizes in the solver's scaled units."""
        return np.asarray(dict(self.effect_typical)[effect])

    @property
    def inverse_typical(self) -> np.ndarray:
        """Per effect column (in column order), one over its typical size in scaled
        units (0 where none is documented): the effect prior's precision scale."""
        typical = np.zeros(self.n_free - len(self.base_cols))
        n_base = len(self.base_cols)
        for effect, cols in self.effect_cols:
            typical[np.asarray(cols, int) - n_base] = self.typical(effect)
        return np.where(typical > 0, 1.0 / np.where(typical > 0, typical, 1.0), 0.0)

    @property
    def effect_index(self) -> tuple[int, ...]:
        """Positions (in ``view.names``) of all effect parameters, in column order."""
        return self.free_index[len(self.base_cols) :]

    @property
    def scales(self) -> np.ndarray:
        return np.asarray(self.view.scales)[list(self.free_index)]

    def model(self, template: EffectModel, p: jax.Array) -> EffectModel:
        """The universal model at physical parameters ``p`` (references from ``template``)."""
        return self.view.from_vector(template, p)


def make_layout(
    base: AbstractKinematicModel, effects: tuple[str, ...], fleet: typing.Any, *, change_points: bool = False
) -> tuple[Layout, EffectModel]:
    """The column layout and the universal model (``base`` wrapped by every
    candidate effect at no effect, references from ``fleet``'s valid records).
    Effect elements ``fleet``'s valid records cannot drive
    (:meth:`heliojax.effects.AbstractEffect.driven`, e.g. the offset of a target no
    record uses) get no column: they stay at no effect and count nowhere. With
    ``change_points``, :class:`heliojax.effects.OffsetStep` (``"change_point"``) comes
    first, before the candidates: its change time is a per-lane entry of the
    parameter vectors (never fitted), set by the caller."""
    candidates = with_effects(base, effects)
    if change_points:
        candidates = add_effects(base, [OffsetStep.nominal(base, fleet.counts.dtype), *candidates.effects])
        effects = (OffsetStep.NAME, *effects)
    template = with_data_references(candidates, fleet)
    view = ParameterView.of(template)
    n_base = ParameterView.of(base).n_parameters
    free = view.free
    base_free = [i for i in range(n_base) if free[i]]
    free_index = list(base_free)
    effect_cols, effect_params, effect_typical, effect_units = [], [], [], []
    start_leaf = len(ParameterView.of(base).leaves)
    offset = n_base
    for k, e in enumerate(effects):
        effect = template.effects[k]
        ev = ParameterView.of(effect)
        driven = effect.driven(fleet)
        cols = [offset + i for i in range(ev.n_parameters) if free[offset + i] and (driven is None or bool(driven[i]))]
        start = len(free_index)
        free_index += cols
        effect_cols.append((e, tuple(range(start, len(free_index)))))
        effect_params.append((e, tuple(view.names[i] for i in cols)))
        effect_units.append((e, tuple(view.units[i] for i in cols)))
        effect_typical.append((e, tuple(float(view.typical[i] or 0.0) / float(view.scales[i]) for i in cols)))
        offset += ev.n_parameters
    del start_leaf
    layout = Layout(
        view=view,
        free_index=tuple(free_index),
        base_cols=tuple(range(len(base_free))),
        effect_cols=tuple(effect_cols),
        effect_param_names=tuple(effect_params),
        effect_typical=tuple(effect_typical),
        effect_units=tuple(effect_units),
    )
    return layout, template


# --------------------------------------------------------------------------------------
# Effects to first order
# --------------------------------------------------------------------------------------
#
# Every effect acts through four additive corrections of a record: the joint angles
# (2), the sun vector (3), the focal spot (3) and the heliostat position (3). Inside a
# fit the corrections are expanded to first order in the effect parameters ``q``
# about an expansion point ``q0`` (with the base parameters of that point):
# ``c(q) = c(q0) + D (q - q0)``. The base model itself stays exact. At the
# expansion point value and gradient are exact, so iterating "expand, fit" is
# Gauss-Newton in ``q``; its fixed point is the exact least-squares solution, and
# every statistic is evaluated exactly (expansion at the reported point). The
# expensive effect graph is evaluated once per expansion, not in every solver step.

N_CORR = 11
CAPS = (0, 4, 8, 12, 16, 24, 32)


def _corrections(model: EffectModel, geometry, counts, context, focal):
    g = model.adjusted_geometry(geometry)
    base_angles = model.inner.joint_angles(g, counts)
    d_angles = model.record_angles(g, counts, context) - base_angles
    d_sun = model.sun(geometry, context) - context.sun
    d_focal = model.spot(focal, context) - focal
    d_pos = g.position - geometry.position
    return jnp.concatenate([d_angles, d_sun, d_focal, d_pos])


def _corrections_lane(layout: Layout, template, p, geometry, counts, context, focal, mask):
    counts, context, focal, use, _ = sanitise(geometry, counts, context, focal, mask)
    eidx = jnp.asarray(layout.effect_index, dtype=jnp.int32)

    def corr(q, c, x, f):
        return _corrections(layout.model(template, p.at[eidx].set(q)), geometry, c, x, f)

    q0 = p[eidx]
    c0 = jax.vmap(lambda c, x, f: corr(q0, c, x, f))(counts, context, focal)
    # reverse mode: N_CORR (11) cotangents instead of one tangent per effect parameter
    # (~30 for the default candidates); 2.5-3x faster, the same D to rounding
    d = jax.vmap(lambda c, x, f: jax.jacrev(corr)(q0, c, x, f))(counts, context, focal)
    return c0, d


def _correction_values_lane(layout: Layout, template, p, geometry, counts, context, focal, mask):
    """``c0`` of :func:`_corrections_lane` alone (no derivative): a fraction of its work."""
    counts, context, focal, use, _ = sanitise(geometry, counts, context, focal, mask)
    model = layout.model(template, p)
    return jax.vmap(lambda c, x, f: _corrections(model, geometry, c, x, f))(counts, context, focal)


def _only_active(lane_fn: Callable, inactive_fn: Callable) -> Callable:
    """A lane function ``(active, *args)``: ``lane_fn(*args)`` where ``active``, else
    ``inactive_fn(*args)`` (zeros of the same structure). A branch, not a select, under
    ``lax.map``: an inactive lane costs nothing (a vmapped batch computes both)."""

    def lane(active, *args):
        return jax.lax.cond(active, lambda: lane_fn(*args), lambda: inactive_fn(*args))

    return lane


def _zero_corrections(layout: Layout, counts, derivative: bool):
    c0 = jnp.zeros((counts.shape[0], N_CORR), counts.dtype)
    if not derivative:
        return c0
    return c0, jnp.zeros((counts.shape[0], N_CORR, len(layout.effect_index)), counts.dtype)


@cached_jit
def _correction_values_compiled(layout, batching: AbstractBatching, template, active, p, records: Records):
    fn = _only_active(
        lambda a, g, c, x, f, m: _correction_values_lane(layout, template, a, g, c, x, f, m),
        lambda a, g, c, x, f, m: _zero_corrections(layout, c, derivative=False),
    )
    return batching.map(fn)(active, p, *records)


@cached_jit
def _corrections_compiled(layout, batching: AbstractBatching, template, active, p, records: Records):
    fn = _only_active(
        lambda a, g, c, x, f, m: _corrections_lane(layout, template, a, g, c, x, f, m),
        lambda a, g, c, x, f, m: _zero_corrections(layout, c, derivative=True),
    )
    return batching.map(fn)(active, p, *records)


def _linear_record(base, tilts, geometry, counts, context, focal, corr):
    geo = eqx.tree_at(lambda g: g.position, geometry, geometry.position + corr[8:11])
    angles = base.joint_angles(geo, counts) + corr[0:2]
    pose = chain_pose(tilts, angles, geo)
    sun = normalize(context.sun + corr[2:5])
    return beam_error_components(pose, sun, focal + corr[5:8])


def _lane_row(layout: Layout, template, geometry, p_exp, p, counts, context, focal, c0, dmat):
    """One record's two residual rows (mrad) at parameters ``p``, with the effects to
    first order about ``p_exp`` (record corrections ``c0 + dmat (q - q_exp)``)."""
    eidx = jnp.asarray(layout.effect_index, dtype=jnp.int32)
    base = layout.model(template, p).inner
    corr = c0 + dmat @ (p[eidx] - p_exp[eidx])
    return _linear_record(base, base.tilts(), geometry, counts, context, focal, corr) * 1e3


def _fit_lane(
    layout: Layout,
    solver,
    max_steps: int,
    cap: int,
    template,
    p0,
    sel,
    sel_valid,
    prior_weight,
    p_exp,
    c0,
    dmat,
    geometry,
    counts,
    context,
    focal,
    mask,
):
    """One lane's Levenberg-Marquardt fit: the base's free parameters plus up to
    ``cap`` effect parameters (solver columns ``sel``, where ``sel_valid``), each
    effect parameter with a Gaussian prior row ``prior_weight * (q - q_none) /
    scale`` (``q_none``: no effect; weight 0: no prior). ``cost`` is that of the
    records' rows alone."""
    counts, context, focal, use, _ = sanitise(geometry, counts, context, focal, mask)
    dtype = counts.dtype
    n_base = len(layout.base_cols)
    all_scales = jnp.asarray(layout.view.scales, dtype)
    base_idx = jnp.asarray(layout.free_index[:n_base], dtype=jnp.int32)
    eff_idx = jnp.asarray(layout.effect_index, dtype=jnp.int32)[sel]

    def to_physical(y):
        p = p0.at[base_idx].add(y[:n_base] * all_scales[base_idx])
        if cap:
            p = p.at[eff_idx].add(jnp.where(sel_valid, y[n_base:], 0.0) * all_scales[eff_idx])
        return p

    def row(y, c, x, f, k, d):
        return _lane_row(layout, template, geometry, p_exp, to_physical(y), c, x, f, k, d)

    # the prior's rows are linear in y: (p0 - q_none) / scale + y, weighted
    weight = jnp.where(sel_valid, prior_weight, 0.0)
    none = layout.view.to_vector(template).astype(dtype)
    prior_at_zero = weight * (p0[eff_idx] - none[eff_idx]) / all_scales[eff_idx]
    prior_jac = jnp.concatenate([jnp.zeros((cap, n_base), dtype), jnp.diag(weight)], axis=1)

    def rows(y):
        r = record_rows(row, y, (counts, context, focal, c0, dmat), use)
        return jnp.concatenate([r, prior_at_zero + weight * y[n_base:]]) if cap else r

    def rows_and_jacobian(y):
        r, jac = record_rows_and_jacobian(row, y, (counts, context, focal, c0, dmat), use)
        if not cap:
            return r, jac
        return jnp.concatenate([r, prior_at_zero + weight * y[n_base:]]), jnp.concatenate([jac, prior_jac])

    residual = residual_with_jacobian(rows, rows_and_jacobian)
    out = solve_least_squares(residual, jnp.zeros(n_base + cap, dtype), solver, max_steps)
    prior_cost = 0.5 * jnp.sum((prior_at_zero + weight * out.value[n_base:]) ** 2) if cap else 0.0
    p = to_physical(out.value)
    n_used = jnp.sum(use)
    n_active = n_base + jnp.sum(sel_valid)
    ok = (2 * n_used > n_active) & jnp.all(jnp.isfinite(p))
    ok = ok & (out.result != optx.RESULTS.nonlinear_divergence)
    p = jnp.where(ok, p, p0)
    cost = out.cost - prior_cost
    return dict(params=p, ok=ok, cost=cost, n_used=n_used.astype(jnp.int32), n_steps=out.n_steps.astype(jnp.int32))


def _not_fitted_lane(p0) -> dict:
    """What :func:`_fit_lane` returns, for an inactive lane: its start, not ``ok``."""
    none = jnp.zeros((), jnp.int32)
    return dict(params=p0, ok=jnp.zeros((), bool), cost=jnp.zeros((), p0.dtype), n_used=none, n_steps=none)


@cached_jit
def _fit_lanes_compiled(layout, solver, max_steps, batching, cap, template, active, lane_inputs, records):
    """The active lanes' fits (:func:`_fit_lane`); ``lane_inputs``: its arguments from
    ``p0`` to ``dmat``, per lane; ``records``: :data:`Records`."""
    fn = _only_active(
        lambda *a: _fit_lane(layout, solver, max_steps, cap, template, *a),
        lambda p0, *a: _not_fitted_lane(p0),
    )
    return batching.map(fn)(active, *lane_inputs, *records)


def _predicted_focal(layout: Layout, template, p, c0, geometry, counts, context, focal):
    """Noise-free focal spots: where the model at ``p`` sends each record's central
    ray, at the measured distance (so the residual there is 0)."""
    base = layout.model(template, p).inner
    tilts = base.tilts()

    def one(c, x, f, k):
        geo = eqx.tree_at(lambda g: g.position, geometry, geometry.position + k[8:11])
        pose = chain_pose(tilts, base.joint_angles(geo, c) + k[0:2], geo)
        ray = reflected_ray(pose, normalize(x.sun + k[2:5]))
        dist = jnp.linalg.norm(f + k[5:8] - pose.centre)
        return pose.centre + dist * ray - k[5:8]

    return jax.vmap(one)(counts, context, focal, c0)


def _jac_lane(layout: Layout, template, p, c0, dmat, geometry, counts, context, focal, mask):
    """Exact residuals at the measured spots; the Jacobian at the model's noise-free
    spots (Fisher scoring). The exact Jacobian holds a term proportional to the
    measurement noise itself (moving the target along the line of sight rescales
    every measured offset), which would make a regressor of the noise; the
    noise-free one is the expected Jacobian and keeps the score tests valid."""
    counts, context, focal, use, _ = sanitise(geometry, counts, context, focal, mask)
    dtype = counts.dtype
    idx = jnp.asarray(layout.free_index, dtype=jnp.int32)
    scales = jnp.asarray(layout.view.scales, dtype)[idx]
    records = (counts, context, focal, c0, dmat)
    r = jax.vmap(lambda *rec: _lane_row(layout, template, geometry, p, p, *rec))(*records)
    r = jnp.where(use[:, None], r, 0.0).reshape(-1)
    predicted = _predicted_focal(layout, template, p, c0, geometry, counts, context, focal)

    def row_at_predicted(y, c, x, f, k, d):
        return _lane_row(layout, template, geometry, p, p.at[idx].add(y * scales), c, x, f, k, d)

    y0 = jnp.zeros(layout.n_free, dtype)
    _, jac = record_rows_and_jacobian(row_at_predicted, y0, (counts, context, predicted, c0, dmat), use)
    return r, jac


def _residual_lane(layout: Layout, template, p, geometry, counts, context, focal, mask):
    """Exact residuals (mrad) of one lane at ``p``, as :func:`_jac_lane` gives them,
    without the Jacobian and without differentiating the effects."""
    counts, context, focal, use, _ = sanitise(geometry, counts, context, focal, mask)
    model = layout.model(template, p)
    base = model.inner
    tilts = base.tilts()

    def row(c, x, f):
        corr = _corrections(model, geometry, c, x, f)
        return _linear_record(base, tilts, geometry, c, x, f, corr) * 1e3

    r = jax.vmap(row)(counts, context, focal)
    return jnp.where(use[:, None], r, 0.0).reshape(-1)


@cached_jit
def _residual_lanes_compiled(layout, batching, template, active, p, records: Records):
    fn = _only_active(
        lambda *a: _residual_lane(layout, template, *a),
        lambda p, g, c, *a: jnp.zeros((2 * c.shape[0],), c.dtype),
    )
    return batching.map(fn)(active, p, *records)


@cached_jit
def _jac_lanes_compiled(layout, batching, template, active, p, c0, dmat, records: Records):
    fn = _only_active(
        lambda *a: _jac_lane(layout, template, *a),
        lambda p, c0, d, g, c, *a: (
            jnp.zeros((2 * c.shape[0],), c.dtype),
            jnp.zeros((2 * c.shape[0], layout.n_free), c.dtype),
        ),
    )
    return batching.map(fn)(active, p, c0, dmat, *records)


@dataclasses.dataclass(frozen=True)
class Lanes:
    """The fleet replicated over ``K + 1`` masks (numpy bookkeeping + device data).

    Attributes:
        data: the fleet's record arrays tiled to ``L = (K + 1) * H`` lanes
            (:data:`Records`); its mask is each lane's training mask.
        eval_data: the same lanes with every valid record unmasked (to evaluate).
        fold: ``(L,)`` fold of each lane (0 = all records).
        heliostat: ``(L,)`` heliostat index of each lane.
        record_fold: ``(H, M)`` fold (1..K) of each record, 0 for invalid ones.
        valid: ``(H, M)`` valid records.
        n_folds: ``K``.
        cross_validated: ``(L,)`` lanes that train (fold 0, and the cross-validation
            lanes with enough training records: :func:`make_lanes`).
    """

    data: Records
    eval_data: Records
    fold: np.ndarray
    heliostat: np.ndarray
    record_fold: np.ndarray
    valid: np.ndarray
    n_folds: int
    cross_validated: np.ndarray

    @property
    def n_heliostats(self) -> int:
        return self.valid.shape[0]

    @property
    def train_mask(self) -> np.ndarray:
        """``(L, M)`` each lane's training records."""
        return np.asarray(self.data[4])

    def lane(self, fold: int, heliostat: int) -> int:
        return fold * self.n_heliostats + heliostat

    def fold_records(self) -> np.ndarray:
        """``(L, M)``: the valid records of each lane's fold (none for fold 0), whether or
        not the lane is cross-validated."""
        rf = self.record_fold[self.heliostat]
        return (rf == self.fold[:, None]) & (self.fold[:, None] > 0) & self.valid[self.heliostat]

    def heldout_mask(self) -> np.ndarray:
        """``(L, M)``: the records each lane holds out (none for fold 0 and for the lanes
        that do not train, :attr:`cross_validated`)."""
        return self.fold_records() & self.cross_validated[:, None]


def _local_days(
    unix_time: np.ndarray, valid: np.ndarray, longitude_deg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(valid, day, timed, days)``: the mask as bool, each record's local day
    (:func:`heliojax.fitting.day_labels`), the valid records with a time, and their
    distinct days in order."""
    valid = np.asarray(valid, bool)
    timed = valid & np.isfinite(np.asarray(unix_time, float))
    day = day_labels(unix_time, longitude_deg)
    return valid, day, timed, np.unique(day[timed])


def fleet_longitude_deg(fleet: typing.Any) -> float:
    """The plant's longitude (deg east) from a fleet's ENU origin, 0 (UTC days) for
    a fleet without one."""
    origin = getattr(fleet, "origin_lla", None)
    return 0.0 if origin is None else float(np.asarray(origin)[1])


def fold_blocks(unix_time: np.ndarray, valid: np.ndarray, longitude_deg: float = 0.0) -> int:
    """Number of blocks :func:`day_folds` deals to the folds: the distinct local days
    of the valid timed records plus one per valid record without a time (``unix_time``:
    s, ``valid``: bool, same shape; ``longitude_deg``: the plant's, deg east)."""
    valid, _, timed, days = _local_days(unix_time, valid, longitude_deg)
    return len(days) + int((valid & ~timed).sum())


def too_few_days_note(blocks: int) -> str | None:
    """Why no effect can be named when the records span fewer than 2 blocks of
    :func:`fold_blocks` (cross-validation by day holds no record out), else None."""
    if blocks >= 2:
        return None
    return (
        f"the records span {blocks} day(s): cross-validation blocked by day holds no record out, so no "
        "effect can pass its held-out test and none will be named"
    )


def day_folds(
    unix_time: np.ndarray, valid: np.ndarray, record_id: np.ndarray | None, n_folds: int, longitude_deg: float = 0.0
) -> np.ndarray:
    """Blocked folds by day (a local mean solar day at ``longitude_deg`` east,
    :func:`heliojax.fitting.day_labels`: records of one day share their errors, and
    a boundary at UTC midnight would split a day of a plant far east or west of
    Greenwich): the fleet's distinct days, in chronological order, are dealt to folds
    ``1..K`` in turn (so every fold spans the season); all records of a day share a
    fold. A record without a time is its own block, dealt after the days in record-id
    order. Invalid records get fold 0."""
    valid, day, timed, days = _local_days(unix_time, valid, longitude_deg)
    out = np.zeros(valid.shape, np.int64)
    out[timed] = np.searchsorted(days, day[timed]) % n_folds + 1  # a day's rank among the fleet's days
    untimed = np.argwhere(valid & ~timed)
    if len(untimed):
        key = np.asarray(record_id)[tuple(untimed.T)] if record_id is not None else np.arange(len(untimed))
        order = np.argsort(key, kind="stable")
        out[tuple(untimed[order].T)] = (len(days) + np.arange(len(order))) % n_folds + 1
    return out


def make_lanes(fleet: typing.Any, n_folds: int, min_training_records: int = 0) -> Lanes:
    """Lanes of ``fleet`` (padded): one per (fold, heliostat), folds by local day.

    A cross-validation lane (fold > 0) keeps its training records only where they are
    at least ``min_training_records`` (discovery: the base model's free parameters, so
    that they determine it twice over, as each segment of the change-point scan must,
    :func:`heliojax.fitting.find_change_points`); a lane with fewer trains on nothing,
    is not fitted and holds nothing out (:attr:`Lanes.cross_validated`). Such a lane's
    fit is not determined by its records: the solver crawled along the directions they
    leave open, to its step limit (on the shared PAINT records, the folds of heliostats
    with 8-12 records: 6-7 training records against 8 free parameters), and its
    held-out predictions were wherever it stopped."""
    valid = np.asarray(fleet.mask, bool)
    rf = day_folds(
        np.asarray(fleet.context.unix_time), valid, np.asarray(fleet.record_id), n_folds, fleet_longitude_deg(fleet)
    )
    h = valid.shape[0]
    fold = np.repeat(np.arange(n_folds + 1), h)
    heli = np.tile(np.arange(h), n_folds + 1)
    train = valid[heli] & ((rf[heli] != fold[:, None]) | (fold[:, None] == 0))
    cross_validated = (fold == 0) | (train.sum(axis=1) >= min_training_records)
    train &= cross_validated[:, None]
    tile = lambda x: jnp.concatenate([x] * (n_folds + 1), axis=0)  # noqa: E731
    geometry, counts, context, focal, _ = jax.tree.map(tile, fleet_records(fleet))
    data = (geometry, counts, context, focal, jnp.asarray(train))
    eval_data = (geometry, counts, context, focal, jnp.asarray(valid[heli]))
    return Lanes(
        data=data,
        eval_data=eval_data,
        fold=fold,
        heliostat=heli,
        record_fold=rf,
        valid=valid,
        n_folds=n_folds,
        cross_validated=cross_validated,
    )


@dataclasses.dataclass(frozen=True)
class Engine:
    """The compiled programs over one set of lanes.

    Attributes:
        layout: the static column layout.
        template: the universal model (references from the data).
        lanes: the lanes.
        solver: the optimistix least-squares solver.
        max_steps: its step limit.
        batching: the strategy over lanes.
        effect_prior: per-heliostat effect parameters get a Gaussian prior of their
            typical size (:func:`heliojax.parameter`'s ``typical``) about no effect.
    """

    layout: Layout
    template: EffectModel
    lanes: Lanes
    solver: optx.AbstractLeastSquaresSolver
    max_steps: int
    batching: AbstractBatching
    effect_prior: bool = True

    @classmethod
    def create(
        cls,
        layout: Layout,
        template: EffectModel,
        lanes: Lanes,
        solver=None,
        max_steps: int = 64,
        batching: AbstractBatching | None = None,
        effect_prior: bool = True,
    ) -> Engine:
        return cls(
            layout,
            template,
            lanes,
            default_solver() if solver is None else solver,
            max_steps,
            default_batching() if batching is None else batching,
            effect_prior,
        )

    def prior_weights(self, noise_mrad: np.ndarray, inverse_typical: np.ndarray | None = None) -> np.ndarray:
        """``(L, E)`` weights of the effect prior's rows per lane and effect column
        (scaled units; see :meth:`fit`): noise over the prior's standard deviation
        (``inverse_typical`` ``(E,)``, default the layout's typical sizes); 0 without a
        prior."""
        noise = np.where(np.isfinite(noise_mrad) & (noise_mrad > 0), noise_mrad, 0.0)
        inv = self.layout.inverse_typical if inverse_typical is None else np.asarray(inverse_typical)
        return noise[:, None] * inv[None, :] * float(self.effect_prior)

    @functools.cached_property
    def groups(self) -> tuple[LaneGroup, ...]:
        """The lanes grouped by record width (see :func:`lane_groups`), each group cut
        into the batching's blocks (:meth:`~heliojax.fitting.AbstractBatching.n_blocks`;
        :func:`split_group`)."""
        return tuple(b for g in lane_groups(self.lanes) for b in split_group(g, self.batching.n_blocks(g.n)))

    @functools.cached_property
    def _fit_records(self) -> tuple[Records, ...]:
        """Each group's training records (taken once: every fit, expansion and
        Jacobian of a workflow reads them, and eager gathers cost ~15 % of a real
        discovery's time when repeated)."""
        return tuple(g.take(self.lanes.data) for g in self.groups)

    @functools.cached_property
    def _eval_records(self) -> tuple[Records, ...]:
        """Each group's valid records (see :attr:`_fit_records`)."""
        return tuple(g.take(self.lanes.eval_data) for g in self.groups)

    def _data(self, k: int, evaluate: bool) -> Records:
        """Group ``k``'s records: all valid ones with ``evaluate``, else the training ones."""
        return (self._eval_records if evaluate else self._fit_records)[k]

    @property
    def skips_inactive_lanes(self) -> bool:
        """Whether a lane left out by ``active`` costs nothing (the batching's
        :attr:`~heliojax.fitting.AbstractBatching.skips_inactive`: ``lax.map``, the CPU
        default, yes; a vmapped batch computes every lane and selects)."""
        return self.batching.skips_inactive

    def _active(self, g: LaneGroup, active: np.ndarray | None) -> jax.Array:
        """Group ``g``'s lanes' flags: every lane, or those of ``active`` ``(L,)``."""
        return jnp.asarray(np.ones(g.index.size, bool) if active is None else np.asarray(active, bool)[g.index])

    def _group_args(self, k: int, p: np.ndarray, evaluate: bool, active: np.ndarray | None) -> tuple:
        """The lane arguments of the per-group programs at ``p`` (group ``k``): the
        flags, the parameters and the records, each batched along the lanes."""
        g = self.groups[k]
        return self._active(g, active), jnp.asarray(p[g.index]), self._data(k, evaluate)

    def _head(self) -> tuple:
        """The static arguments most per-group programs start with."""
        return self.layout, self.batching, self.template

    def _each_group(self, work) -> list:
        """``[work(k) for k in groups]``, by the batching's
        :meth:`~heliojax.fitting.AbstractBatching.each` (concurrently, one host thread
        per core, under :class:`heliojax.Threaded`: each group's records stay on the
        device, and its outputs are never joined to another's)."""
        return self.batching.each(work, len(self.groups))

    def expand(self, p, evaluate: bool = False, derivative_from=None, active: np.ndarray | None = None):
        """First-order effect corrections ``(c0, D)`` at ``p`` (device arrays), one
        pair per lane group. With ``derivative_from`` (an earlier expansion of the same
        lanes and ``evaluate``), only ``c0`` is evaluated at ``p`` and ``D`` is taken
        from it: the derivative of the effect graph is most of the cost, and it
        changes little between the iterations of a fit (see ``fit_state``). With
        ``active`` ``(L,)``, the other lanes are skipped (zeros), here and in
        :meth:`fit`, :meth:`jacobian` and :meth:`residuals`."""
        p = np.asarray(p)
        if derivative_from is not None:
            assert len(derivative_from) == len(self.groups)
            values = self._each_group(
                lambda k: _correction_values_compiled(*self._head(), *self._group_args(k, p, evaluate, active))
            )
            return tuple((c0, old[1]) for c0, old in zip(values, derivative_from, strict=True))
        return tuple(
            self._each_group(lambda k: _corrections_compiled(*self._head(), *self._group_args(k, p, evaluate, active)))
        )

    def fit(
        self,
        p0: np.ndarray,
        effect_cols,
        p_exp: np.ndarray,
        expansion,
        noise_mrad: np.ndarray | None = None,
        active: np.ndarray | None = None,
        inverse_typical: np.ndarray | None = None,
    ) -> dict:
        """One Levenberg-Marquardt fit of every lane from ``p0``: the base's free
        parameters and the effect columns ``effect_cols`` (positions among the
        effect columns) free, the effects expanded about ``p_exp`` (``expansion``:
        :meth:`expand` at ``p_exp``). The solver's width is bucketed (0, 4, 8, 12, 16,
        24, 32 effect columns) so that few programs are compiled. ``cost`` is
        ``0.5 * sum r^2`` of the linearised model's record rows (the effect prior's
        rows, with ``effect_prior``, left out). With ``effect_prior``, ``noise_mrad``
        ``(L,)`` is each lane's noise per residual component: the prior rows are
        ``noise * (q - q_none) / typical``, so that the fit is the posterior mode of
        Gaussian records and a Gaussian prior (no prior where it is None);
        ``inverse_typical`` ``(E,)``: one over the prior's standard deviation per
        effect column (:meth:`prior_weights`)."""
        k = len(effect_cols)
        cap = next(c for c in CAPS if c >= k) if k <= CAPS[-1] else k
        p0, p_exp = np.asarray(p0), np.asarray(p_exp)
        sel = np.zeros((p0.shape[0], cap), np.int32)
        valid = np.zeros((p0.shape[0], cap), bool)
        sel[:, :k] = np.asarray(effect_cols, np.int32)
        valid[:, :k] = True
        weight = np.zeros((p0.shape[0], cap))
        if self.effect_prior and k and noise_mrad is not None:
            weight[:, :k] = self.prior_weights(noise_mrad, inverse_typical)[:, np.asarray(effect_cols, int)]
        assert len(expansion) == len(self.groups)

        def fit_group(k: int) -> dict:
            g, (c0, dmat) = self.groups[k], expansion[k]
            return _fit_lanes_compiled(
                self.layout,
                self.solver,
                self.max_steps,
                self.batching,
                cap,
                self.template,
                self._active(g, active),
                (*(jnp.asarray(x[g.index]) for x in (p0, sel, valid, weight, p_exp)), c0, dmat),
                self._data(k, False),
            )

        parts = self._each_group(fit_group)
        return {key: _scatter([np.asarray(o[key]) for o in parts], self.groups, p0.shape[0]) for key in parts[0]}

    def jacobian(
        self, p: np.ndarray, evaluate: bool = False, expansion=None, active: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Exact residuals ``(L, 2M)`` (mrad) and the expected (noise-free) Jacobian
        ``(L, 2M, F)`` (mrad per scaled unit) at ``p``; rows of records outside the training mask (with
        ``evaluate``: outside the valid records) are zero. ``expansion``: :meth:`expand`
        at ``p`` with the same ``evaluate``, when the caller has it (else computed here)."""
        p = np.asarray(p)

        def jacobian_group(k: int) -> tuple[np.ndarray, np.ndarray]:
            flags, params, data = self._group_args(k, p, evaluate, active)
            head = self._head()
            c0, dmat = _corrections_compiled(*head, flags, params, data) if expansion is None else expansion[k]
            r, j = _jac_lanes_compiled(*head, flags, params, c0, dmat, data)
            return np.asarray(r), np.asarray(j)

        rs, js = map(list, zip(*self._each_group(jacobian_group), strict=True))
        n_lanes, width = p.shape[0], 2 * self.lanes.valid.shape[1]
        return _scatter(rs, self.groups, n_lanes, width), _scatter(js, self.groups, n_lanes, width)

    def residuals(self, p: np.ndarray, evaluate: bool = False, active: np.ndarray | None = None) -> np.ndarray:
        """The exact residuals of :meth:`jacobian` alone, ``(L, 2M)`` mrad (no Jacobian,
        no first-order expansion: a fraction of its work)."""
        p = np.asarray(p)
        rs = self._each_group(
            lambda k: np.asarray(_residual_lanes_compiled(*self._head(), *self._group_args(k, p, evaluate, active)))
        )
        return _scatter(rs, self.groups, p.shape[0], 2 * self.lanes.valid.shape[1])


@dataclasses.dataclass(frozen=True)
class LaneGroup:
    """Lanes whose heliostats' records all lie within the first ``width`` record slots.

    Attributes:
        index: ``(L_g,)`` lane indices; the first ``n`` are the group's, the rest repeat
            the last one (padding to a multiple of :data:`LANE_MULTIPLE`, so that few
            lane counts are compiled).
        n: the group's lanes.
        width: record slots kept (a power of two, at most the fleet's).
    """

    index: np.ndarray
    n: int
    width: int

    def take(self, records: Records) -> Records:
        """``records`` of the group's lanes, cut to ``width`` record slots."""
        i = jnp.asarray(self.index)
        geometry, *per_record = records
        geometry = jax.tree.map(lambda x: x[i], geometry)
        per_record = jax.tree.map(lambda x: x[i, : self.width], tuple(per_record))
        return (geometry, *per_record)


LANE_MULTIPLE = 16
"""Lane counts of a group are padded to a multiple of this."""
MIN_WIDTH = 16
"""The narrowest group (record slots)."""


def lane_groups(lanes: Lanes) -> tuple[LaneGroup, ...]:
    """The lanes grouped by the record slots their heliostat uses.

    Every lane is padded to the fleet's widest heliostat; with 8 to 164 records per
    heliostat (the shared PAINT records, median 29), most of every lane's work went
    to padding. A heliostat's width is one past its last valid record, rounded up to
    a power of two (at least :data:`MIN_WIDTH`, at most the fleet's); lanes of equal
    width form a group, fitted by its own compiled programs. With one width there is
    one group of all lanes in order, the same program as without groups."""
    n_slots = lanes.valid.shape[1]
    last = np.where(lanes.valid.any(axis=1), n_slots - np.argmax(lanes.valid[:, ::-1], axis=1), 0)
    width = np.minimum(2 ** np.ceil(np.log2(np.maximum(last, MIN_WIDTH))).astype(int), n_slots)
    lane_width = width[lanes.heliostat]
    groups = []
    for w in np.unique(lane_width):
        idx = np.flatnonzero(lane_width == w)
        if idx.size == lane_width.size:
            return (LaneGroup(idx, idx.size, n_slots),)
        pad = -idx.size % LANE_MULTIPLE
        groups.append(LaneGroup(np.concatenate([idx, np.full(pad, idx[-1])]), idx.size, int(w)))
    return tuple(groups)


def split_group(group: LaneGroup, n_blocks: int) -> tuple[LaneGroup, ...]:
    """``group`` cut into ``n_blocks`` groups of one width by the blocks' one rule
    (:func:`heliojax.fitting.block_lanes`: lane ``i`` of it into block ``i mod
    n_blocks``), each padded to the ``1 / n_blocks`` share of the group's padded lane
    count (one program shape per block count)."""
    if n_blocks <= 1:
        return (group,)
    real = group.index[: group.n]
    size = -(-group.index.size // n_blocks)
    return tuple(
        LaneGroup(real[i], -(-(group.n - k) // n_blocks), group.width)  # its real lanes: k, k + B, ... < n
        for k, i in enumerate(block_lanes(group.n, n_blocks, size))
    )


def _scatter(parts: list[np.ndarray], groups: tuple[LaneGroup, ...], n_lanes: int, width: int | None = None):
    """Per-group lane outputs back into one ``(n_lanes, ...)`` array; with ``width``,
    axis 1 is zero-padded from each group's ``2 * width`` rows to ``width``."""
    first = parts[0]
    shape = (n_lanes,) + ((width,) + first.shape[2:] if width is not None else first.shape[1:])
    out = np.zeros(shape, first.dtype)
    for g, part in zip(groups, parts, strict=True):
        rows = part[: g.n]
        if width is None:
            out[g.index[: g.n]] = rows
        else:
            out[g.index[: g.n], : rows.shape[1]] = rows
    return out
