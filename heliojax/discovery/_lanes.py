"""Lanes: the fleet replicated once per cross-validation fold, and the compiled
fit / Jacobian programs that run over all lanes at once.

A *lane* is one heliostat under one record mask: lane ``(f, h)`` holds
heliostat ``h`` with the records of every fold but ``f`` (``f = 0``: all
records). Fitting all lanes in one compiled program gives the full-data fit
and every cross-validation fit in one call.

The fit is the same Levenberg-Marquardt problem as :func:`heliojax.fit_fleet`
(tangent-plane residuals in mrad, scaled parameters, masked records replaced
by :func:`heliojax._calibration._sanitise`, heliostats mapped in one compiled
program), over *one* model specification that carries the base parameters and
the parameters of every candidate effect. Which effect parameters move is
dynamic data (solver columns ``sel``), only the solver's width is static and
bucketed, so every candidate, every fold and every step of the discovery
reuses a handful of compiled programs. (``fit_fleet`` fixes the free set
statically, which would recompile per candidate, and counts every free
parameter of the specification against a heliostat's records.)
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._calibration import (
    CalibrationData,
    FitConfig,
    ModelSpec,
    _batched,
    _sanitise,
    default_strategy,
)


@dataclasses.dataclass(frozen=True)
class Layout:
    """Static column layout of the discovery's universal specification.

    Attributes:
        spec: base + all candidate effects (:func:`heliojax.effects.with_effects`).
        free_index: positions (in ``spec.names``) of the columns the solver sees:
            the base's free parameters, then every effect parameter.
        base_cols: solver columns of the base's free parameters.
        effect_cols: effect name -> its solver columns.
        effect_param_names: effect name -> its parameter names.
    """

    spec: ModelSpec
    free_index: tuple[int, ...]
    base_cols: tuple[int, ...]
    effect_cols: tuple[tuple[str, tuple[int, ...]], ...]
    effect_param_names: tuple[tuple[str, tuple[str, ...]], ...]
    effect_typical: tuple[tuple[str, tuple[float, ...]], ...] = ()

    @property
    def n_free(self) -> int:
        return len(self.free_index)

    def cols(self, effect: str) -> tuple[int, ...]:
        return dict(self.effect_cols)[effect]

    def params(self, effect: str) -> tuple[str, ...]:
        return dict(self.effect_param_names)[effect]

    def typical(self, effect: str) -> np.ndarray:
        """The effect's typical sizes in the solver's scaled units."""
        return np.asarray(dict(self.effect_typical)[effect])

    @property
    def effect_index(self) -> tuple[int, ...]:
        """Positions (in ``spec.names``) of all effect parameters, in column order."""
        return self.free_index[len(self.base_cols):]

    @property
    def scales(self) -> np.ndarray:
        return np.asarray(self.spec.scales)[list(self.free_index)]


def make_layout(base_spec: ModelSpec, effects: tuple[str, ...]) -> Layout:
    from ..effects import with_effects
    from ..effects._spec import base_kind_of, effect_class

    spec = with_effects(base_spec, effects)
    kind = base_kind_of(spec)
    base_free = [spec.names.index(n) for n in base_spec.free]
    free_index = list(base_free)
    effect_cols = []
    effect_params = []
    effect_typical = []
    for e in effects:
        cls = effect_class(e)
        names = cls.param_names(kind)
        start = len(free_index)
        free_index += [spec.names.index(n) for n in names]
        effect_cols.append((e, tuple(range(start, len(free_index)))))
        effect_params.append((e, tuple(names)))
        effect_typical.append((e, tuple(float(t) / float(sc) for t, sc in
                                        zip(cls.typical_sizes(kind), cls.param_scales(kind)))))
    return Layout(
        spec=spec,
        free_index=tuple(free_index),
        base_cols=tuple(range(len(base_free))),
        effect_cols=tuple(effect_cols),
        effect_param_names=tuple(effect_params),
        effect_typical=tuple(effect_typical),
    )


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


def _corrections(model, geometry, counts, context, focal):
    g = model._geometry(geometry)
    base_angles = model.base.joint_angles(g, counts)
    d_angles = model._angles(g, counts, context) - base_angles
    d_sun = model.sun(geometry, context) - context.sun
    d_focal = model._focal(focal, context) - focal
    d_pos = g.position - geometry.position
    return jnp.concatenate([d_angles, d_sun, d_focal, d_pos])


def _corrections_lane(layout: "Layout", p, geometry, counts, context, focal, mask):
    spec = layout.spec
    counts, context, focal, use, _ = _sanitise(geometry, counts, context, focal, mask)
    eidx = jnp.asarray(layout.effect_index, dtype=jnp.int32)

    def corr(q, c, x, f):
        return _corrections(spec.builder(p.at[eidx].set(q)), geometry, c, x, f)

    q0 = p[eidx]
    c0 = jax.vmap(lambda c, x, f: corr(q0, c, x, f))(counts, context, focal)
    d = jax.vmap(lambda c, x, f: jax.jacfwd(corr)(q0, c, x, f))(counts, context, focal)
    return c0, d


@eqx.filter_jit
def _corrections_compiled(layout, strategy, p, data: CalibrationData):
    fn = lambda a, g, c, x, f, m: _corrections_lane(layout, a, g, c, x, f, m)  # noqa: E731
    return _batched(fn, strategy, 64)(p, data.geometry, data.counts, data.context, data.focal_spot, data.mask)


def _linear_record(base, tilts, geometry, counts, context, focal, corr):
    from .._geometry import normalize
    from .._kinematics import beam_error_components, chain_pose

    geo = eqx.tree_at(lambda g: g.position, geometry, geometry.position + corr[8:11])
    angles = base.joint_angles(geo, counts) + corr[0:2]
    pose = chain_pose(tilts, angles, geo)
    sun = normalize(context.sun + corr[2:5])
    return beam_error_components(pose, sun, focal + corr[5:8])


def _lane_residual_fn(layout: "Layout", geometry, counts, context, focal, use, p_exp, c0, dmat):
    """``p -> residuals (2M,)`` in mrad with the effects to first order about ``p_exp``."""
    builder = layout.spec.builder
    eidx = jnp.asarray(layout.effect_index, dtype=jnp.int32)

    def fn(p):
        base = builder.base_builder(p[: builder.n_base])
        tilts = base.tilts()
        dq = p[eidx] - p_exp[eidx]
        corr = c0 + jnp.einsum("mij,j->mi", dmat, dq)
        r = jax.vmap(lambda c, x, f, k: _linear_record(base, tilts, geometry, c, x, f, k))(counts, context, focal, corr)
        return jnp.where(use[:, None], r * 1e3, 0.0).reshape(-1)

    return fn


def _fit_lane(layout: "Layout", config: FitConfig, cap: int, p0, sel, sel_valid, p_exp, c0, dmat, geometry, counts,
              context, focal, mask):
    """One lane's Levenberg-Marquardt fit: the base's free parameters plus up to
    ``cap`` effect parameters (solver columns ``sel``, where ``sel_valid``)."""
    counts, context, focal, use, _ = _sanitise(geometry, counts, context, focal, mask)
    dtype = counts.dtype
    n_base = len(layout.base_cols)
    all_scales = jnp.asarray(layout.spec.scales, dtype)
    base_idx = jnp.asarray(layout.free_index[:n_base], dtype=jnp.int32)
    eff_idx = jnp.asarray(layout.effect_index, dtype=jnp.int32)[sel]
    res = _lane_residual_fn(layout, geometry, counts, context, focal, use, p_exp, c0, dmat)

    def to_physical(y):
        p = p0.at[base_idx].add(y[:n_base] * all_scales[base_idx])
        if cap:
            p = p.at[eff_idx].add(jnp.where(sel_valid, y[n_base:], 0.0) * all_scales[eff_idx])
        return p

    y0 = jnp.zeros(n_base + cap, dtype)
    solver = optx.LevenbergMarquardt(rtol=config.rtol, atol=config.atol)
    sol = optx.least_squares(lambda y, _: res(to_physical(y)), solver, y0, max_steps=config.max_steps,
                             throw=False)
    p = to_physical(sol.value)
    cost = jnp.sum(sol.state.f_info.residual**2)
    n_used = jnp.sum(use)
    n_active = n_base + jnp.sum(sel_valid)
    ok = (2 * n_used > n_active) & jnp.all(jnp.isfinite(p))
    ok = ok & (sol.result != optx.RESULTS.nonlinear_divergence)
    p = jnp.where(ok, p, p0)
    return dict(params=p, ok=ok, cost=cost, n_used=n_used.astype(jnp.int32),
                n_steps=sol.stats["num_steps"].astype(jnp.int32))


@eqx.filter_jit
def _fit_lanes_compiled(layout, config, strategy, cap, p0, sel, sel_valid, p_exp, c0, dmat, data: CalibrationData):
    fn = lambda *a: _fit_lane(layout, config, cap, *a)  # noqa: E731
    return _batched(fn, strategy, config.chunk_size)(
        p0, sel, sel_valid, p_exp, c0, dmat, data.geometry, data.counts, data.context, data.focal_spot, data.mask
    )


def _predicted_focal(layout: "Layout", p, c0, geometry, counts, context, focal):
    """Noise-free focal spots: where the model at ``p`` sends each record's central
    ray, at the measured distance (so the residual there is 0)."""
    from .._geometry import normalize
    from .._kinematics import chain_pose, reflected_ray

    builder = layout.spec.builder
    base = builder.base_builder(p[: builder.n_base])
    tilts = base.tilts()

    def one(c, x, f, k):
        geo = eqx.tree_at(lambda g: g.position, geometry, geometry.position + k[8:11])
        pose = chain_pose(tilts, base.joint_angles(geo, c) + k[0:2], geo)
        ray = reflected_ray(pose, normalize(x.sun + k[2:5]))
        dist = jnp.linalg.norm(f + k[5:8] - pose.centre)
        return pose.centre + dist * ray - k[5:8]

    return jax.vmap(one)(counts, context, focal, c0)


def _jac_lane(layout: "Layout", p, c0, dmat, geometry, counts, context, focal, mask):
    """Exact residuals at the measured spots; the Jacobian at the model's noise-free
    spots (Fisher scoring). The exact Jacobian holds a term proportional to the
    measurement noise itself (moving the target along the line of sight rescales
    every measured offset), which would make a regressor of the noise; the
    noise-free one is the expected Jacobian and keeps the score tests valid."""
    counts, context, focal, use, _ = _sanitise(geometry, counts, context, focal, mask)
    dtype = counts.dtype
    idx = jnp.asarray(layout.free_index, dtype=jnp.int32)
    scales = jnp.asarray(layout.spec.scales, dtype)[idx]
    res = _lane_residual_fn(layout, geometry, counts, context, focal, use, p, c0, dmat)
    predicted = _predicted_focal(layout, p, c0, geometry, counts, context, focal)
    res_pred = _lane_residual_fn(layout, geometry, counts, context, predicted, use, p, c0, dmat)
    y0 = jnp.zeros(layout.n_free, dtype)
    r = res(p)
    _, lin = jax.linearize(lambda y: res_pred(p.at[idx].add(y * scales)), y0)
    jac = jax.vmap(lin, out_axes=1)(jnp.eye(layout.n_free, dtype=dtype))
    return r, jac


@eqx.filter_jit
def _jac_lanes_compiled(layout, strategy, p, c0, dmat, data: CalibrationData):
    fn = lambda *a: _jac_lane(layout, *a)  # noqa: E731
    return _batched(fn, strategy, 64)(p, c0, dmat, data.geometry, data.counts, data.context, data.focal_spot,
                                      data.mask)


@dataclasses.dataclass(frozen=True)
class Lanes:
    """The fleet replicated over ``K + 1`` masks (numpy bookkeeping + device data).

    Attributes:
        data: :class:`~heliojax.CalibrationData` with ``L = (K + 1) * H`` lanes; its
            mask is each lane's training mask.
        eval_data: the same lanes with every valid record unmasked (to evaluate).
        fold: ``(L,)`` fold of each lane (0 = all records).
        heliostat: ``(L,)`` heliostat index of each lane.
        record_fold: ``(H, M)`` fold (1..K) of each record, 0 for invalid ones.
        valid: ``(H, M)`` valid records.
        n_folds: ``K``.
    """

    data: CalibrationData
    eval_data: CalibrationData
    fold: np.ndarray
    heliostat: np.ndarray
    record_fold: np.ndarray
    valid: np.ndarray
    n_folds: int

    @property
    def n_heliostats(self) -> int:
        return self.valid.shape[0]

    def lane(self, fold: int, heliostat: int) -> int:
        return fold * self.n_heliostats + heliostat

    def heldout_mask(self) -> np.ndarray:
        """``(L, M)``: the records each lane holds out (none for fold 0)."""
        rf = self.record_fold[self.heliostat]
        return (rf == self.fold[:, None]) & (self.fold[:, None] > 0) & self.valid[self.heliostat]


def day_folds(unix_time: np.ndarray, valid: np.ndarray, record_id: np.ndarray | None, n_folds: int) -> np.ndarray:
    """Blocked folds by UTC day: the fleet's distinct days, in chronological order,
    are dealt to folds ``1..K`` in turn (so every fold spans the season); all
    records of a day share a fold. A record without a time is its own block,
    dealt after the days in record-id order. Invalid records get fold 0."""
    t = np.asarray(unix_time, float)
    valid = np.asarray(valid, bool)
    day = np.floor(t / 86400.0)
    timed = valid & np.isfinite(day)
    days = np.unique(day[timed])
    rank = {d: i for i, d in enumerate(days)}
    out = np.zeros(valid.shape, np.int64)
    for (i, j) in zip(*np.nonzero(timed)):
        out[i, j] = rank[day[i, j]] % n_folds + 1
    untimed = np.argwhere(valid & ~np.isfinite(day))
    if len(untimed):
        key = (np.asarray(record_id)[tuple(untimed.T)] if record_id is not None else np.arange(len(untimed)))
        order = np.argsort(key, kind="stable")
        for k, idx in enumerate(order):
            i, j = untimed[idx]
            out[i, j] = (len(days) + k) % n_folds + 1
    return out


def make_lanes(data: CalibrationData, record_id, n_folds: int) -> Lanes:
    valid = np.asarray(data.mask, bool)
    rf = day_folds(np.asarray(data.context.unix_time), valid, record_id, n_folds)
    h = valid.shape[0]
    n_lanes = (n_folds + 1) * h
    fold = np.repeat(np.arange(n_folds + 1), h)
    heli = np.tile(np.arange(h), n_folds + 1)
    train = valid[heli] & ((rf[heli] != fold[:, None]) | (fold[:, None] == 0))
    tile = lambda x: jnp.concatenate([x] * (n_folds + 1), axis=0)  # noqa: E731
    base = CalibrationData(
        geometry=jax.tree_util.tree_map(tile, data.geometry),
        counts=tile(data.counts),
        context=jax.tree_util.tree_map(tile, data.context),
        focal_spot=tile(data.focal_spot),
        mask=jnp.asarray(train),
    )
    eval_data = eqx.tree_at(lambda d: d.mask, base, jnp.asarray(valid[heli]))
    assert base.counts.shape[0] == n_lanes
    return Lanes(data=base, eval_data=eval_data, fold=fold, heliostat=heli, record_fold=rf, valid=valid,
                 n_folds=n_folds)


@dataclasses.dataclass(frozen=True)
class Engine:
    """The compiled programs over one set of lanes."""

    layout: Layout
    lanes: Lanes
    config: FitConfig
    strategy: str

    @classmethod
    def create(cls, layout: Layout, lanes: Lanes, config: FitConfig) -> "Engine":
        strategy = config.strategy if config.strategy != "auto" else default_strategy()
        return cls(layout, lanes, config, strategy)

    def _data(self, evaluate: bool):
        return self.lanes.eval_data if evaluate else self.lanes.data

    def expand(self, p, evaluate: bool = False):
        """First-order effect corrections ``(c0, D)`` at ``p`` (device arrays)."""
        return _corrections_compiled(self.layout, self.strategy, jnp.asarray(p), self._data(evaluate))

    def fit(self, p0: np.ndarray, effect_cols, p_exp: np.ndarray, expansion) -> dict:
        """One Levenberg-Marquardt fit of every lane from ``p0``: the base's free
        parameters and the effect columns ``effect_cols`` (positions among the
        effect columns) free, the effects expanded about ``p_exp``. The solver's
        width is bucketed (0, 4, 8, 12, 16, 24, 32 effect columns) so that few
        programs are compiled."""
        c0, dmat = expansion
        k = len(effect_cols)
        cap = next(c for c in CAPS if c >= k) if k <= CAPS[-1] else k
        n_lanes = p0.shape[0]
        sel = np.zeros((n_lanes, cap), np.int32)
        valid = np.zeros((n_lanes, cap), bool)
        sel[:, :k] = np.asarray(effect_cols, np.int32)
        valid[:, :k] = True
        out = _fit_lanes_compiled(self.layout, self.config, self.strategy, cap, jnp.asarray(p0), jnp.asarray(sel),
                                  jnp.asarray(valid), jnp.asarray(p_exp), c0, dmat, self.lanes.data)
        return {k_: np.asarray(v) for k_, v in out.items()}

    def jacobian(self, p: np.ndarray, evaluate: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Exact residuals ``(L, 2M)`` (mrad) and the expected (noise-free) Jacobian
        ``(L, 2M, F)`` (mrad per scaled unit) at ``p``; rows of records outside the training mask (with
        ``evaluate``: outside the valid records) are zero."""
        data = self._data(evaluate)
        c0, dmat = _corrections_compiled(self.layout, self.strategy, jnp.asarray(p), data)
        r, j = _jac_lanes_compiled(self.layout, self.strategy, jnp.asarray(p), c0, dmat, data)
        return np.asarray(r), np.asarray(j)
