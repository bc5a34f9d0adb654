"""Fleet-wide calibration: optimistix Levenberg-Marquardt of every heliostat at once.

One compiled program fits all heliostats of a (padded) fleet. Each heliostat's
problem is

    minimise  sum_records |r_i(y)|^2  +  sum_priors ((p_j - p_j0) * noise / sigma_j)^2

where ``r_i`` are the two tangent-plane components of the beam pointing error of
record ``i`` (:func:`heliojax.beam_error_components`, in mrad) and ``y`` is the
model's parameter vector in *scaled* units (10 mrad for angles, 0.01 for gear
ratios and relative scales, 1 cm for lengths) so that the solver's tolerances read
in physical units (0.1 micro-radian) and optimistix LM's initial damping (1 in
scaled units) is mild against ``J^T J`` of a typical calibration (5 instead of 8
LM steps on simulated Stone fleets). The Jacobian is computed per record in
reverse mode and handed to the solver through a ``jax.custom_jvp``. Padded or non-finite records are masked out (their
inputs are replaced by a dummy record before any arithmetic, so they contribute
neither values nor NaN gradients).

The heliostat axis is batched by ``jax.vmap`` (wide batches for GPUs), by
``jax.lax.map`` (sequential lanes: on CPU this avoids the batched while-loop
running every lane to the slowest one), or by chunked ``lax.map`` (``batch_size``);
:func:`default_strategy` chooses per backend. Float64 is required: enable it with
``jax.config.update("jax_enable_x64", True)`` (the CLI does).
"""

from __future__ import annotations

import dataclasses
import enum
import warnings
import typing
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ._kinematics import (
    AbstractKinematicModel,
    ActuatorModel,
    HeliostatGeometry,
    RecordContext,
    StoneModel,
)

# --------------------------------------------------------------------------------------
# Status codes
# --------------------------------------------------------------------------------------


class FitStatus(enum.IntEnum):
    """Per-heliostat outcome of a fit."""

    CONVERGED = 0
    MAX_STEPS = 1
    DIVERGED = 2
    NON_FINITE_INPUT = 3
    TOO_FEW_RECORDS = 4
    FAILED = 5
    PADDING = 6

    @property
    def label(self) -> str:
        return self.name.lower()


# --------------------------------------------------------------------------------------
# Parameter specifications: vector <-> model
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """How a model's parameters map to the solver's scaled vector.

    Attributes:
        kind: model name (``"stone8"``, ``"actuator"``, or a base name with effects
            such as ``"stone8+backlash"``).
        names: all parameter names of the model, in vector order.
        scales: physical units per unit of the scaled vector, per name.
        free: names that are fitted (the rest stay at their start values).
        units: unit label per name (for reports).
        nominal: nominal (uncalibrated) physical value per name.
        builder: ``builder(p) -> model`` from the physical vector ``p`` (a module-level,
            hashable function: the spec is a static argument of compiled fits).
    """

    kind: str
    names: tuple[str, ...]
    scales: tuple[float, ...]
    free: tuple[str, ...]
    units: tuple[str, ...]
    nominal: tuple[float, ...]
    builder: typing.Callable[[Float[Array, " P"]], AbstractKinematicModel]

    def __post_init__(self):
        unknown = set(self.free) - set(self.names)
        if unknown:
            raise ValueError(f"unknown parameters {sorted(unknown)} for model {self.kind!r}")
        n = len(self.names)
        if not (len(self.scales) == len(self.units) == len(self.nominal) == n):
            raise ValueError("ModelSpec: names, scales, units and nominal must have equal lengths")

    @property
    def free_index(self) -> tuple[int, ...]:
        return tuple(self.names.index(n) for n in self.free)

    @property
    def n_free(self) -> int:
        return len(self.free)

    def nominal_vector(self, dtype=jnp.float64) -> Float[Array, " P"]:
        """Physical values of all parameters of the nominal model."""
        return jnp.asarray(self.nominal, dtype)

    def nominal_model(self, dtype=jnp.float64) -> AbstractKinematicModel:
        return self.builder(self.nominal_vector(dtype))

    def physical_to_model(self, p: Float[Array, " P"]) -> AbstractKinematicModel:
        return self.builder(p)

    def scaled_to_physical(self, y: Float[Array, " F"], base: Float[Array, " P"]) -> Float[Array, " P"]:
        scales = jnp.asarray(self.scales, base.dtype)
        idx = jnp.asarray(self.free_index, dtype=jnp.int32)
        return base.at[idx].add(y * scales[idx])

    def scaled_to_model(self, y, base) -> AbstractKinematicModel:
        return self.physical_to_model(self.scaled_to_physical(y, base))


def build_stone_model(p: Float[Array, " 8"]) -> StoneModel:
    """:class:`StoneModel` from ``(alpha, beta, gamma, delta, theta_k, tau_k, gr1, gr2)``."""
    return StoneModel(*[p[i] for i in range(8)])


def build_actuator_model(p: Float[Array, " 10"]) -> ActuatorModel:
    """:class:`ActuatorModel` from its 10-vector (order ``ActuatorModel.PARAM_NAMES``)."""
    return ActuatorModel(
        alpha=p[0], beta=p[1], gamma=p[2], delta=p[3],
        angle_offset=p[4:6], increment_scale=p[6:8], stroke_offset=p[8:10],
    )


STONE8 = ModelSpec(
    kind="stone8",
    names=StoneModel.PARAM_NAMES,
    scales=(1e-2,) * 8,
    free=StoneModel.PARAM_NAMES,
    units=("rad",) * 6 + ("1", "1"),
    nominal=(0.0,) * 6 + (1.0, 1.0),
    builder=build_stone_model,
)
"""The eight Stone parameters, all fitted."""

ACTUATOR = ModelSpec(
    kind="actuator",
    names=ActuatorModel.PARAM_NAMES,
    scales=(1e-2,) * 10,
    free=ActuatorModel.PARAM_NAMES[:8],
    units=("rad",) * 6 + ("1", "1") + ("m", "m"),
    nominal=(0.0,) * 10,
    builder=build_actuator_model,
)
"""The linear-actuator model: four chain tilts, two angle offsets and two increment
scales fitted (the identifiable set); the two stroke offsets are nearly collinear
with the angle offsets and increment scales over a calibration's range and stay
nominal unless freed (with a prior)."""


def model_spec(kind: "str | ModelSpec", free: typing.Sequence[str] | None = None) -> ModelSpec:
    """The :class:`ModelSpec` of ``"stone8"`` or ``"actuator"``, optionally with a
    different set of free parameters."""
    if isinstance(kind, ModelSpec):
        return kind if free is None else dataclasses.replace(kind, free=tuple(free))
    base = {"stone8": STONE8, "actuator": ACTUATOR}.get(kind)
    if base is None:
        raise ValueError(f"unknown model {kind!r}; expected 'stone8' or 'actuator'")
    if free is None:
        return base
    return dataclasses.replace(base, free=tuple(free))


# --------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------


STRATEGIES = ("auto", "vmap", "chunked", "map")


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Solver settings (static: changing them recompiles).

    Attributes:
        rtol, atol: optimistix LM tolerances on the scaled parameters (units of
            10 mrad, 0.01, 1 cm) and on the cost (mrad^2): ``atol = 1e-5`` means
            0.1 micro-radian.
        max_steps: LM step limit; kept small so one slow lane cannot stall a batch.
        prior_sigma: Tikhonov prior toward nominal, ``{name: sigma in physical
            units}``; empty = no prior.
        noise_mrad: assumed measurement noise that scales the prior rows.
        strategy: ``"auto" | "vmap" | "chunked" | "map"``.
        chunk_size: lanes per chunk for ``"chunked"``.
        jacobian: ``"record_rev"`` (reverse mode per record, handed to the solver as
            an explicit matrix through a ``jax.custom_jvp``) or ``"fwd"``
            (optimistix's own forward-mode linearisation, for models that are not
            reverse-mode differentiable).
    """

    rtol: float = 1e-8
    atol: float = 1e-5
    max_steps: int = 64
    prior_sigma: tuple[tuple[str, float], ...] = ()
    noise_mrad: float = 0.5
    strategy: str = "auto"
    chunk_size: int = 64
    jacobian: str = "record_rev"

    def __post_init__(self):
        if self.jacobian not in ("record_rev", "fwd"):
            raise ValueError(f"jacobian must be 'record_rev' or 'fwd', got {self.jacobian!r}")
        if self.strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {STRATEGIES}, got {self.strategy!r}")
        if isinstance(self.prior_sigma, Mapping):
            object.__setattr__(self, "prior_sigma", tuple(sorted(self.prior_sigma.items())))
        for name, sigma in self.prior_sigma:
            if not sigma > 0:
                raise ValueError(f"prior sigma of {name!r} must be > 0, got {sigma}")


DEFAULT_WEAK_PRIOR = (("delta", 5e-3), ("gamma", 5e-3))
"""A prior for the Stone model's weakly identified pair: gamma and delta are
nearly collinear with theta_k over typical elevation ranges."""


def default_strategy(backend: str | None = None) -> str:
    """``"map"`` on CPU (sequential lanes beat vmap's lock-step while-loop there),
    ``"vmap"`` on accelerators."""
    backend = backend or jax.default_backend()
    return "map" if backend == "cpu" else "vmap"


# --------------------------------------------------------------------------------------
# Batch of problems
# --------------------------------------------------------------------------------------


@typing.final
class CalibrationData(eqx.Module):
    """The arrays a fit needs, batched over heliostats ``H`` and records ``M``.

    Attributes:
        geometry: batched :class:`HeliostatGeometry`.
        counts: ``(H, M, 2)`` motor counts.
        context: batched ``(H, M)`` :class:`RecordContext` (sun, time, weather).
        focal_spot: ``(H, M, 3)`` ENU m.
        mask: ``(H, M)`` records to use.
    """

    geometry: HeliostatGeometry
    counts: Float[Array, "H M 2"]
    context: RecordContext
    focal_spot: Float[Array, "H M 3"]
    mask: Bool[Array, "H M"]

    @property
    def sun(self) -> Float[Array, "H M 3"]:
        return self.context.sun

    @classmethod
    def from_fleet(cls, fleet, mask=None) -> "CalibrationData":
        """From a :class:`heliojax.Fleet` and an optional ``(H, M)`` record mask
        (ANDed with the fleet's validity mask)."""
        m = fleet.mask if mask is None else (jnp.asarray(mask) & fleet.mask)
        return cls(
            geometry=fleet.geometry,
            counts=fleet.counts,
            context=fleet.context,
            focal_spot=fleet.focal_spot,
            mask=m,
        )


def _finite_record(counts, context, focal):
    return (
        jnp.all(jnp.isfinite(counts), -1)
        & jnp.all(jnp.isfinite(context.sun), -1)
        & jnp.all(jnp.isfinite(focal), -1)
    )


def _sanitise(geometry, counts, context, focal, mask):
    """Replace masked or non-finite records by a harmless dummy (mid-range counts,
    sun in the south, spot 100 m south, weather NaN -> 0 there) so no NaN reaches
    values or gradients. Weather of *used* records stays as it is (NaN = unknown;
    effects that need it treat NaN themselves)."""
    finite = _finite_record(counts, context, focal)
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


def _record_residuals(model, geometry, counts, context, focal):
    def one(c, x, f):
        return model.beam_components(geometry, c, x, f)

    return jax.vmap(one)(counts, context, focal)


@typing.final
class FitResult(eqx.Module):
    """Outcome of :func:`fit_fleet`; arrays batched over heliostats.

    Attributes:
        params: ``(H, P)`` physical parameter values (rad, 1, m), order ``spec.names``.
        std: ``(H, P)`` Gauss-Newton standard errors (0 for fixed parameters, NaN
            where undetermined).
        status: ``(H,)`` :class:`FitStatus` codes.
        n_steps: ``(H,)`` LM steps taken.
        n_used: ``(H,)`` records used.
        rms_mrad: ``(H,)`` RMS beam pointing error over the fitted records.
        final_cost: ``(H,)`` 0.5 * sum of squared residuals (mrad^2, priors included).
        spec: the :class:`ModelSpec` (static).
    """

    params: Float[Array, "H P"]
    std: Float[Array, "H P"]
    status: Int[Array, " H"]
    n_steps: Int[Array, " H"]
    n_used: Int[Array, " H"]
    rms_mrad: Float[Array, " H"]
    final_cost: Float[Array, " H"]
    spec: ModelSpec = eqx.field(static=True)

    def model(self, i: int) -> AbstractKinematicModel:
        """The fitted model of heliostat ``i``."""
        return self.spec.physical_to_model(self.params[i])

    def models(self) -> AbstractKinematicModel:
        """All fitted models as one batched model (vmap over its leading axis)."""
        return jax.vmap(self.spec.physical_to_model)(self.params)

    def status_labels(self) -> list[str]:
        return [FitStatus(int(s)).label for s in np.asarray(self.status)]


def _psd_inverse(a):
    """Inverse of a symmetric positive semi-definite matrix via a Jacobi-scaled
    Cholesky factorisation; NaN where it is singular."""
    d = jnp.sqrt(jnp.clip(jnp.diag(a), 1e-300))
    scaled = a / d[:, None] / d[None, :]
    chol = jnp.linalg.cholesky(scaled)
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    inv_l = jax.scipy.linalg.solve_triangular(chol, eye, lower=True)
    return (inv_l.T @ inv_l) / d[:, None] / d[None, :]


def _fit_one(spec: ModelSpec, config: FitConfig, base, geometry, counts, context, focal, mask):
    counts, context, focal, use, bad_input = _sanitise(geometry, counts, context, focal, mask)
    dtype = counts.dtype
    n_used = jnp.sum(use)
    prior_names = tuple(n for n, _ in config.prior_sigma if n in spec.names)
    prior_idx = jnp.asarray([spec.names.index(n) for n in prior_names], dtype=jnp.int32)
    prior_sig = jnp.asarray([s for n, s in config.prior_sigma if n in spec.names], dtype)
    nominal = spec.nominal_vector(dtype)

    def record_residual(y, c, x, f):
        r = spec.scaled_to_model(y, base).beam_components(geometry, c, x, f) * 1e3
        return r, r

    def prior_residual(y):
        p = spec.scaled_to_physical(y, base)
        return (p[prior_idx] - nominal[prior_idx]) / prior_sig * config.noise_mrad

    def residual(y):
        r = _record_residuals(spec.scaled_to_model(y, base), geometry, counts, context, focal) * 1e3
        r = jnp.where(use[:, None], r, 0.0).reshape(-1)
        return jnp.concatenate([r, prior_residual(y)]) if prior_names else r

    def residual_and_jacobian(y):
        # Each record's two residuals depend on all parameters: reverse mode per
        # record (2 cotangents) is ~3x cheaper than forward mode (n_free tangents).
        jac, r = jax.vmap(jax.jacrev(record_residual, has_aux=True), (None, 0, 0, 0))(y, counts, context, focal)
        r = jnp.where(use[:, None], r, 0.0).reshape(-1)
        jac = jnp.where(use[:, None, None], jac, 0.0).reshape(-1, y.shape[0])
        if prior_names:
            r = jnp.concatenate([r, prior_residual(y)])
            jac = jnp.concatenate([jac, jax.jacfwd(prior_residual)(y)])
        return r, jac

    if config.jacobian == "record_rev":
        # optimistix linearises the residual (jax.linearize); with this rule the
        # linearisation is the explicit Jacobian matrix (cheap to materialise),
        # not a replay of the whole forward graph per tangent.
        residual_cj = jax.custom_jvp(residual)

        @residual_cj.defjvp
        def _residual_jvp(primals, tangents):
            (y,), (t,) = primals, tangents
            r, jac = residual_and_jacobian(y)
            return r, jac @ t

        residual_fn = lambda y, _: residual_cj(y)  # noqa: E731
    else:
        residual_fn = lambda y, _: residual(y)  # noqa: E731

    y0 = jnp.zeros(spec.n_free, dtype)
    solver = optx.LevenbergMarquardt(rtol=config.rtol, atol=config.atol)
    sol = optx.least_squares(residual_fn, solver, y0, max_steps=config.max_steps, throw=False)
    y = sol.value
    # Residuals and Jacobian at the accepted point come from the solver's state
    # (evaluating them again would inline the whole forward graph once more).
    r1 = sol.state.f_info.residual
    final_cost = 0.5 * jnp.sum(r1**2)

    # Gauss-Newton covariance of the free parameters (scaled units -> physical).
    # The solver's own linearisation at the accepted point (no second Jacobian).
    jac = sol.state.f_info.jac.as_matrix()
    jtj = jac.T @ jac
    n_res = 2 * n_used
    dof = jnp.maximum(n_res - spec.n_free, 1)
    data_r = r1[: 2 * counts.shape[0]]
    sigma2 = jnp.sum(data_r**2) / dof
    cov = _psd_inverse(jtj) * sigma2
    scales = jnp.asarray(spec.scales, dtype)[jnp.asarray(spec.free_index)]
    std_free = jnp.sqrt(jnp.clip(jnp.diag(cov), 0.0)) * scales
    std = jnp.zeros_like(base).at[jnp.asarray(spec.free_index)].set(std_free)

    params = spec.scaled_to_physical(y, base)
    rms = jnp.sqrt(jnp.sum(jnp.where(use[:, None], (r1[: 2 * counts.shape[0]].reshape(-1, 2)) ** 2, 0.0)) / jnp.maximum(n_used, 1))

    result = sol.result
    status = jnp.where(
        result == optx.RESULTS.successful,
        FitStatus.CONVERGED,
        jnp.where(
            result == optx.RESULTS.nonlinear_max_steps_reached,
            FitStatus.MAX_STEPS,
            jnp.where(result == optx.RESULTS.nonlinear_divergence, FitStatus.DIVERGED, FitStatus.FAILED),
        ),
    )
    status = jnp.where(jnp.all(jnp.isfinite(params)) & jnp.isfinite(final_cost), status, FitStatus.DIVERGED)
    status = jnp.where(bad_input, FitStatus.NON_FINITE_INPUT, status)
    too_few = n_used < spec.n_free
    status = jnp.where(too_few, FitStatus.TOO_FEW_RECORDS, status)
    status = jnp.where(jnp.any(mask), status, FitStatus.PADDING)
    # An unconstrained fit is never reported: keep nominal values where too few records.
    params = jnp.where(too_few, base, params)
    std = jnp.where(too_few, jnp.nan, std)
    return dict(
        params=params,
        std=std,
        status=status.astype(jnp.int32),
        n_steps=sol.stats["num_steps"].astype(jnp.int32),
        n_used=n_used.astype(jnp.int32),
        rms_mrad=rms,
        final_cost=final_cost,
    )


def _batched(fn, strategy: str, chunk_size: int):
    if strategy == "vmap":
        return jax.vmap(fn)
    if strategy == "map":
        return lambda *xs: jax.lax.map(lambda a: fn(*a), xs)
    if strategy == "chunked":
        return lambda *xs: jax.lax.map(lambda a: fn(*a), xs, batch_size=chunk_size)
    raise ValueError(strategy)


@eqx.filter_jit
def _fit_compiled(spec, config, strategy, base, data: CalibrationData):
    fn = lambda b, g, c, s, f, m: _fit_one(spec, config, b, g, c, s, f, m)  # noqa: E731
    out = _batched(fn, strategy, config.chunk_size)(
        base, data.geometry, data.counts, data.context, data.focal_spot, data.mask
    )
    return out


def fit_fleet(
    data: CalibrationData,
    spec: ModelSpec | str = "stone8",
    config: FitConfig = FitConfig(),
    initial: Float[Array, "H P"] | None = None,
) -> FitResult:
    """Fit every heliostat of ``data`` in one compiled program.

    Args:
        data: batched arrays (pad with :func:`heliojax.pad_fleet` to a shape bucket
            so new fleet sizes reuse the compiled program).
        spec: a :class:`ModelSpec` or ``"stone8"`` / ``"actuator"``.
        config: solver settings.
        initial: ``(H, P)`` physical start values (default: nominal); also the
            values of the parameters that are not free.

    Returns:
        A :class:`FitResult`.
    """
    if isinstance(spec, str):
        spec = model_spec(spec)
    strategy = config.strategy if config.strategy != "auto" else default_strategy()
    h = data.counts.shape[0]
    dtype = data.counts.dtype
    if initial is None:
        initial = jnp.broadcast_to(spec.nominal_vector(dtype), (h, len(spec.names)))
    out = _fit_compiled(spec, config, strategy, jnp.asarray(initial, dtype), data)
    return FitResult(spec=spec, **out)


# --------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------


@eqx.filter_jit
def beam_errors_mrad(
    models: AbstractKinematicModel, geometry: HeliostatGeometry, counts, context: RecordContext, focal, mask
) -> Float[Array, "H M"]:
    """Beam pointing error (mrad) of every record ``(H, M)`` under batched
    ``models``; NaN where ``mask`` is False or an input is non-finite."""

    def per_heliostat(model, g, c, x, f, m):
        c2, x2, f2, use, _ = _sanitise(g, c, x, f, m)
        e = jax.vmap(lambda ci, xi, fi: model.beam_error(g, ci, xi, fi))(c2, x2, f2) * 1e3
        return jnp.where(use, e, jnp.nan)

    return jax.vmap(per_heliostat)(models, geometry, counts, context, focal, mask)


def fleet_beam_errors_mrad(result_or_models, fleet, mask=None) -> Float[Array, "H M"]:
    """Per-record beam error (mrad) of a fitted fleet (NaN outside ``mask``)."""
    models = result_or_models.models() if isinstance(result_or_models, FitResult) else result_or_models
    m = fleet.mask if mask is None else (jnp.asarray(mask) & fleet.mask)
    return beam_errors_mrad(models, fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, m)


def nominal_models(spec: ModelSpec | str, n: int, dtype=jnp.float64) -> AbstractKinematicModel:
    """``n`` nominal models batched along a leading axis."""
    if isinstance(spec, str):
        spec = model_spec(spec)
    vec = jnp.broadcast_to(spec.nominal_vector(dtype), (n, len(spec.names)))
    return jax.vmap(spec.physical_to_model)(vec)


def fleet_typical_actuators(geometry: HeliostatGeometry, valid: Bool[Array, " H"]):
    """Median actuator values over the valid heliostats (the start geometry for
    heliostats whose nominal properties are far off, e.g. PAINT's BF41)."""
    valid = np.asarray(valid)
    act = geometry.actuators

    def med(x):
        x = np.asarray(x)
        return jnp.asarray(np.median(x[valid], axis=0), x.dtype)

    return jax.tree_util.tree_map(med, act)


def choose_start_geometry(fleet, spec: ModelSpec | str = "stone8"):
    """Per heliostat, the better start of two: its own nominal geometry, or its
    geometry with the fleet's typical (median) actuator values.

    The choice is by the uncalibrated median beam error of the heliostat's own
    records, so no threshold is involved. Returns ``(geometry, replaced)`` with
    ``replaced`` a boolean ``(H,)`` array.
    """
    if isinstance(spec, str):
        spec = model_spec(spec)
    h = fleet.counts.shape[0]
    has = np.asarray(jnp.any(fleet.mask, axis=1))
    if not has.any():
        return fleet.geometry, np.zeros(h, bool)
    typical = fleet_typical_actuators(fleet.geometry, has)
    typ_act = jax.tree_util.tree_map(lambda t, x: jnp.broadcast_to(t, x.shape), typical, fleet.geometry.actuators)
    alt = HeliostatGeometry.build(
        fleet.geometry.position,
        typ_act,
        fleet.geometry.joint_translation_1,
        fleet.geometry.joint_translation_2,
        fleet.geometry.concentrator_translation,
    )
    models = nominal_models(spec, h, fleet.counts.dtype)
    e_own = beam_errors_mrad(models, fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, fleet.mask)
    e_alt = beam_errors_mrad(models, alt, fleet.counts, fleet.context, fleet.focal_spot, fleet.mask)
    def row_median(e):
        e = np.where(np.isfinite(np.asarray(e)), np.asarray(e), np.nan)
        with warnings.catch_warnings():  # all-NaN rows (no records) are expected
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmedian(e, axis=1)

    med_own = row_median(e_own)
    med_alt = row_median(e_alt)
    med_own = np.where(np.isnan(med_own), np.inf, med_own)
    med_alt = np.where(np.isnan(med_alt), np.inf, med_alt)
    replaced = has & (med_alt < med_own)
    geometry = jax.tree_util.tree_map(
        lambda a, b: jnp.where(jnp.asarray(replaced).reshape((-1,) + (1,) * (a.ndim - 1)), b, a),
        fleet.geometry,
        alt,
    )
    return geometry, replaced


__all__ = [
    "ACTUATOR",
    "DEFAULT_WEAK_PRIOR",
    "STONE8",
    "STRATEGIES",
    "CalibrationData",
    "FitConfig",
    "FitResult",
    "FitStatus",
    "ModelSpec",
    "beam_errors_mrad",
    "build_actuator_model",
    "build_stone_model",
    "choose_start_geometry",
    "default_strategy",
    "fit_fleet",
    "fleet_beam_errors_mrad",
    "model_spec",
    "nominal_models",
]
