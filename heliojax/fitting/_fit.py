"""The one fit core: ``fit(model0, fleet, ...) -> FitSolution``.

Every heliostat of a (padded) fleet is fitted in one compiled program. Each
heliostat's problem is

    minimise  0.5 * sum_records |loss.row(r_i(y))|^2  +  0.5 * |prior.rows(p(y))|^2

where ``r_i`` are the two tangent-plane components of the beam pointing error of
record ``i`` (:func:`heliojax.beam_error_components`, mrad) under the model
``p(y) = p0 + y * scale`` on the free parameters (the model pytree's free set,
scales from the fields' metadata: :class:`heliojax.ParameterView`). The scales
(10 mrad for angles, 0.01 for gear ratios and relative scales, 1 cm for lengths)
make the solver's tolerances read in physical units and optimistix LM's initial
damping mild against ``J^T J``. The Jacobian is computed per record in reverse mode
(two cotangents per record) and handed to the solver through a ``jax.custom_jvp``.
Padded or non-finite records are masked out (replaced by a dummy record before any
arithmetic, so they contribute neither values nor NaN gradients).

Calibration, sharding and multi-host, discovery and the neural workflow all call
:func:`fit` (or, for residual functions of their own, :func:`solve_least_squares`).
Float64 is required: ``jax.config.update("jax_enable_x64", True)``.
"""

from __future__ import annotations

import functools
import time
import typing
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._errors import ConfigError
from .._geometry import check_unit_vectors, products_by_reduction
from .._heliostat import HeliostatGeometry, RecordContext
from .._kinematics import AbstractKinematicModel
from .._limits import MAX_FIT_STEPS, count_problem
from .._parameters import ParameterView, and_masks, broadcast_model, is_batched, on_host
from .._programs import cached_jit, compile_cached, program_jit
from ._batching import AbstractBatching, Vmap, default_batching
from ._loss import AbstractLoss, LeastSquares
from ._prior import AbstractPrior, GaussianPrior, NoPrior
from ._records import sanitise
from ._status import FitStatus

DEFAULT_RTOL = 1e-8
DEFAULT_ATOL = 1e-5
DEFAULT_MAX_STEPS = 64
DEFAULT_INITIAL_DAMPING = 1e-6
"""Levenberg-Marquardt's first damping ``lambda_0`` (added to ``J'J`` in scaled
parameter units): Gauss-Newton's step first, damped only once a step fails.

The solver's parameters are scaled (:func:`heliojax.parameter`'s ``scale``: one scaled
unit is 10 mrad on an angle), so a record moves a beam by ~10-20 mrad per scaled unit
and every direction its records determine has a curvature ``J'J`` of ~10^2 per record
or more; ``lambda_0 = 1e-6`` leaves those steps undamped and gives the directions no
record determines (a lane's absorbed effect columns) no step. optimistix's default,
``lambda_0 = 1``, damped weakly determined directions (curvature ~1) by half at every
step until the trust region had grown: discovery's lane fits took 7-8 steps from a
start near their solution, and 3.3-3.6 with this value (the shared PAINT records,
2026-12-05; the folds of heliostats with a few records, nearly as many rows as unknowns,
run to the step limit under either value). A step that fails raises ``lambda`` fourfold
(the classical trust region), so a start far from the solution costs a few rejected
steps at most."""


def _no_verbose(**kwargs: typing.Any) -> None:
    del kwargs


@typing.final
class ToleranceTrustRegion(optx.AbstractSearch):
    """optimistix's :class:`optimistix.ClassicalTrustRegion`, except that a step the
    solver's own termination test calls converged is accepted even when rounding
    makes the cost rise.

    At a minimum the predicted reduction of a Levenberg-Marquardt step is far below
    the rounding noise of the cost (about ``1e-13`` relative for the beam errors), so
    the classical test rejects the step, shrinks the trust region and tries again,
    until the step underflows: a fit started at (or reaching) its minimum spent up to
    16 further steps there. A step within the termination tolerances (parameter
    change ``<= atol + rtol |y|`` and residual change ``<= atol + rtol |r|``, both in
    ``norm``) moves the solution by less than the solver resolves, so accepting it
    costs nothing and ends the solve at once. Every other step is judged exactly as
    by the classical trust region.

    The first trust region is ``initial_step_size`` (the damped Newton descent's
    ``1 / lambda``), not optimistix's 1: see :data:`DEFAULT_INITIAL_DAMPING`.

    Attributes:
        rtol, atol: the solver's termination tolerances.
        norm: the solver's norm.
        initial_step_size: the first step's trust region, ``1 / lambda_0``.
        classical: the trust region that judges every other step.
    """

    rtol: float
    atol: float
    norm: Callable[[typing.Any], Array] = optx.max_norm
    initial_step_size: float = 1.0 / DEFAULT_INITIAL_DAMPING
    classical: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion()

    def __check_init__(self):
        if not self.initial_step_size > 0:
            raise ValueError(f"initial_step_size must be positive, got {self.initial_step_size!r}")

    def init(self, y, f_info_struct):
        state = self.classical.init(y, f_info_struct)
        return eqx.tree_at(
            lambda s: s.step_size, state, jnp.asarray(self.initial_step_size, jnp.result_type(state.step_size))
        )

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, new_state = self.classical.step(first_step, y, y_eval, f_info, f_eval_info, state)
        y_diff = jax.tree.map(lambda a, b: a - b, y_eval, y)
        f_diff = jax.tree.map(lambda a, b: a - b, f_eval_info.residual, f_info.residual)
        converged = (self.norm(y_diff) <= self.atol + self.rtol * self.norm(y_eval)) & (
            self.norm(f_diff) <= self.atol + self.rtol * self.norm(f_eval_info.residual)
        )
        rescued = converged & ~accept
        # a rescued step keeps the trust region it was proposed with
        new_state = jax.tree.map(lambda old, new: jnp.where(rescued, old, new), state, new_state)
        step_size = jnp.where(rescued, jnp.asarray(state.step_size, jnp.result_type(step_size)), step_size)
        return step_size, accept | converged, result, new_state


@typing.final
class LevenbergMarquardt(optx.AbstractGaussNewton):
    """optimistix's Levenberg-Marquardt (damped Newton descent, classical trust
    region, Cauchy termination) with the trust region of :class:`ToleranceTrustRegion`:
    a step already within the termination tolerances is accepted, so that a fit at its
    minimum stops instead of shrinking its trust region through rounding noise; and the
    first step is Gauss-Newton's (damping ``initial_damping``, default
    :data:`DEFAULT_INITIAL_DAMPING`), not one damped by optimistix's ``lambda = 1``.

    Attributes:
        rtol, atol: termination tolerances (parameter and residual change).
        norm: norm of the termination test.
        descent: the damped Newton descent (its linear solver: QR or Cholesky).
        search: the trust region.
        verbose: optimistix's progress callback (silent).
    """

    rtol: float
    atol: float
    norm: Callable[[typing.Any], Array]
    descent: optx.DampedNewtonDescent
    search: ToleranceTrustRegion
    verbose: Callable[..., None]

    def __init__(
        self,
        rtol: float,
        atol: float,
        linear_solver: lx.AbstractLinearSolver | None = None,
        norm: Callable[[typing.Any], Array] = optx.max_norm,
        initial_damping: float = DEFAULT_INITIAL_DAMPING,
    ):
        self.rtol = rtol
        self.atol = atol
        self.norm = norm
        self.descent = optx.DampedNewtonDescent(linear_solver=lx.QR() if linear_solver is None else linear_solver)
        self.search = ToleranceTrustRegion(rtol=rtol, atol=atol, norm=norm, initial_step_size=1.0 / initial_damping)
        self.verbose = _no_verbose


def default_solver(backend: str | None = None) -> LevenbergMarquardt:
    """Levenberg-Marquardt (:class:`LevenbergMarquardt`) with tolerances on the scaled
    parameters: ``atol = 1e-5`` scaled units = 0.1 micro-radian on angles.

    The damped step's linear solve depends on the backend (``backend``, default JAX's
    default backend), as the batching does (:func:`default_batching`):

    * CPU: QR of the stacked ``(R + F) x F`` Jacobian (optimistix's default).
    * accelerators: Cholesky of the ``F x F`` normal equations
      (``lineax.Normal(lineax.Cholesky())``). A batch of QRs of matrices taller than
      32 rows runs on CUDA as one solver call per matrix; on an H200 a 1,000 x 100
      fleet fitted in 1.37 s by QR and in 0.036 s by Cholesky (``benchmarks/
      calibration_speed.py --linear-solver qr,cholesky``). The damping keeps the
      normal matrix positive definite; the parameters agree with QR's to the solver's
      tolerance (``tests/test_calibration.py``).
    """
    backend = backend or jax.default_backend()
    if backend == "cpu":
        return LevenbergMarquardt(rtol=DEFAULT_RTOL, atol=DEFAULT_ATOL)
    return LevenbergMarquardt(rtol=DEFAULT_RTOL, atol=DEFAULT_ATOL, linear_solver=lx.Normal(lx.Cholesky()))


class LeastSquaresOutcome(typing.NamedTuple):
    """What :func:`solve_least_squares` returns for one problem."""

    value: Float[Array, " F"]
    residual: Float[Array, " R"]
    jacobian: Float[Array, "R F"]
    cost: Float[Array, ""]
    result: optx.RESULTS
    n_steps: Int[Array, ""]


def solve_least_squares(
    residual_fn: Callable[[Float[Array, " F"]], Float[Array, " R"]],
    y0: Float[Array, " F"],
    solver: optx.AbstractLeastSquaresSolver,
    max_steps: int,
) -> LeastSquaresOutcome:
    """Run ``solver`` on ``residual_fn`` from ``y0`` (never throws). The cost is
    ``0.5 * sum(residual**2)`` at the accepted point, the Jacobian the solver's own
    linearisation there (no second evaluation)."""
    sol = optx.least_squares(lambda y, _: residual_fn(y), solver, y0, max_steps=max_steps, throw=False)
    residual = sol.state.f_info.residual
    jac = sol.state.f_info.jac.as_matrix()
    return LeastSquaresOutcome(
        value=sol.value,
        residual=residual,
        jacobian=jac,
        cost=0.5 * jnp.sum(residual**2),
        result=sol.result,
        n_steps=sol.stats["num_steps"],
    )


def record_rows(
    row: Callable[..., Float[Array, " k"]],
    y: Float[Array, " F"],
    records: tuple[typing.Any, ...],
    use: Bool[Array, " M"],
) -> Float[Array, " Mk"]:
    """Stacked residual rows of ``M`` records, as :func:`record_rows_and_jacobian`
    gives them, without the Jacobian (rows of records not in ``use`` are zero)."""
    r = jax.vmap(row, (None,) + (0,) * len(records))(y, *records)
    return jnp.where(use[:, None], r, 0.0).reshape(-1)


def record_rows_and_jacobian(
    row: Callable[..., Float[Array, " k"]],
    y: Float[Array, " F"],
    records: tuple[typing.Any, ...],
    use: Bool[Array, " M"],
) -> tuple[Float[Array, " Mk"], Float[Array, "Mk F"]]:
    """Stacked residual rows of ``M`` records and their Jacobian.

    ``row(y, *record)`` gives one record's ``k`` rows; ``records`` are pytrees with a
    leading ``M`` axis. Each record's rows depend on all ``F`` parameters, so the
    Jacobian is taken per record in reverse mode (``k`` cotangents), ~3x cheaper for
    ``k = 2``, ``F = 8`` than forward mode (``F`` tangents). Rows of records not in
    ``use`` are zero, as are their Jacobian rows.
    """

    def both(y, *record):
        r = row(y, *record)
        return r, r

    jac, r = jax.vmap(jax.jacrev(both, has_aux=True), (None,) + (0,) * len(records))(y, *records)
    r = jnp.where(use[:, None], r, 0.0).reshape(-1)
    jac = jnp.where(use[:, None, None], jac, 0.0).reshape(-1, y.shape[0])
    return r, jac


def residual_with_jacobian(
    rows: Callable[[Float[Array, " F"]], Float[Array, " R"]],
    residual_and_jacobian: Callable[[Float[Array, " F"]], tuple[Float[Array, " R"], Float[Array, "R F"]]],
) -> Callable[[Float[Array, " F"]], Float[Array, " R"]]:
    """The residual function ``y -> r`` (``rows``, the same values as the first
    output of ``residual_and_jacobian``) whose linearisation (what optimistix's
    least-squares solvers take, via ``jax.linearize``) is the explicit Jacobian
    matrix of ``residual_and_jacobian``, not a replay of the forward graph per
    tangent. The solvers run only the linearisation; ``rows`` is what they trace
    for the output's shape (several times per compiled solve), so without the
    Jacobian's reverse pass in it the solve traces ~25 % faster."""

    @jax.custom_jvp
    def residual(y):
        return rows(y)

    @residual.defjvp
    def _residual_jvp(primals, tangents):
        (y,), (t,) = primals, tangents
        r, jac = residual_and_jacobian(y)
        # On accelerators as multiply-and-reduce (see ``products_by_reduction``).
        if products_by_reduction():
            return r, jnp.sum(jac * t[None, :], axis=-1)
        return r, jac @ t

    return residual


def psd_inverse(a: Float[Array, "F F"]) -> Float[Array, "F F"]:
    """Inverse of a symmetric positive semi-definite matrix via a Jacobi-scaled
    Cholesky factorisation; NaN where it is singular.

    A parameter with an all-zero row and column (no record and no prior row
    depends on it, e.g. a survey-target slot that none of a heliostat's records
    uses) is not determined: it is left out of the inversion and its row and column
    of the result are zero (:func:`fit` reports its standard deviation as NaN), so
    that the determined parameters keep a finite covariance."""
    diag = jnp.diag(a)
    dead = diag <= 0.0
    d = jnp.sqrt(jnp.where(dead, 1.0, jnp.clip(diag, 1e-300)))
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    scaled = jnp.where(dead[:, None] | dead[None, :], eye, a / d[:, None] / d[None, :])
    chol = jnp.linalg.cholesky(scaled)
    inv_l = jax.scipy.linalg.solve_triangular(chol, eye, lower=True)
    inv = (inv_l.T @ inv_l) / d[:, None] / d[None, :]
    return jnp.where(dead[:, None] | dead[None, :], 0.0, inv)


def status_code(result: optx.RESULTS) -> Int[Array, ""]:
    """:class:`FitStatus` of an optimistix result."""
    return jnp.where(
        result == optx.RESULTS.successful,
        FitStatus.CONVERGED,
        jnp.where(
            result == optx.RESULTS.nonlinear_max_steps_reached,
            FitStatus.MAX_STEPS,
            jnp.where(result == optx.RESULTS.nonlinear_divergence, FitStatus.DIVERGED, FitStatus.FAILED),
        ),
    )


@typing.final
class FitSolution(eqx.Module):
    """Outcome of :func:`fit`; arrays batched over heliostats ``H``.

    Attributes:
        model: the fitted models, one pytree batched along a leading axis ``H``
            (``heliostat_model(i)`` gives one).
        std: ``(H, P)`` Gauss-Newton standard errors in physical units, vector order
            of ``view`` (0 for fixed parameters, NaN where undetermined).
        covariance: ``(H, F, F)`` covariance of the free parameters, physical units
            (zero rows and columns for a parameter that nothing determines, see
            :func:`psd_inverse`).
        status: ``(H,)`` :class:`FitStatus` codes.
        n_steps: ``(H,)`` solver steps (1 for a heliostat with too few records: its
            records are not fitted).
        n_used: ``(H,)`` records used.
        rms_mrad: ``(H,)`` RMS beam pointing error over the fitted records (mrad;
            NaN with too few records).
        cost: ``(H,)`` ``0.5 * sum of squared rows`` (mrad^2, prior rows included).
        noise_mrad: ``(H,)`` residual standard deviation per component (mrad),
            ``sqrt(sum r^2 / (2 n - F))`` of the data rows (NaN with too few records).
        loo_mrad: ``(H, M)`` linearised leave-one-out beam error of every record
            used (mrad; NaN for records not used): the error the fit would leave on
            the record had it been fitted without it, ``|(I - H_ii)^-1 b_i|`` with
            ``b_i`` the record's two beam error components and ``H_ii`` its 2 x 2
            block of the hat matrix ``J (J^T J)^-1 J^T`` (loss weights and prior
            rows included; exact for a linear model). An out-of-sample error from a
            single fit: a heliostat whose median is not below its uncalibrated error
            does not predict better than nominal.
        residual_mrad: ``(H, M, 2)`` residual components of every record at the fitted
            model (mrad, the tangent-plane beam error of
            :func:`heliojax.fleet_residuals_mrad`; NaN for records not used; at the
            start model for a heliostat with too few records).
        view: the :class:`heliojax.ParameterView` (names, units, free set); static.
    """

    model: AbstractKinematicModel
    std: Float[Array, "H P"]
    covariance: Float[Array, "H F F"]
    status: Int[Array, " H"]
    n_steps: Int[Array, " H"]
    n_used: Int[Array, " H"]
    rms_mrad: Float[Array, " H"]
    cost: Float[Array, " H"]
    noise_mrad: Float[Array, " H"]
    loo_mrad: Float[Array, "H M"]
    residual_mrad: Float[Array, "H M 2"]
    view: ParameterView = eqx.field(static=True)

    @property
    def n_heliostats(self) -> int:
        return int(jnp.shape(self.status)[0])

    def fitted(self) -> np.ndarray:
        """``(H,)`` host booleans: the heliostat has a usable fit (converged, or stopped at
        the step limit); the others keep their start model."""
        return np.isin(np.asarray(self.status), (FitStatus.CONVERGED, FitStatus.MAX_STEPS))

    def parameters(self) -> Float[Array, "H P"]:
        """Physical parameter values ``(H, P)`` in the view's vector order."""
        return self.view.to_vector(self.model)

    def heliostat_model(self, i: int) -> AbstractKinematicModel:
        """The fitted model of heliostat ``i``.

        Raises:
            ValueError: ``i`` not a whole number in ``[0, H)`` (-1 had been the last
                heliostat, True a batch of one, 99 or 1.5 an IndexError of NumPy)."""
        traced = isinstance(i, jax.core.Tracer)  # pyright: ignore[reportAttributeAccessIssue]
        if not traced and isinstance(i, (np.ndarray, jax.Array)) and i.ndim == 0 and i.dtype.kind in "iu":
            i = int(i)  # e.g. jnp.argmax(solution.rms_mrad)
        problem = None if traced else count_problem(i, self.n_heliostats - 1, minimum=0)
        if problem is not None:
            raise ValueError(f"heliostat_model: i {problem} (the index of one of the {self.n_heliostats} heliostats)")
        if on_host(*(x for x in jax.tree.leaves(self.model) if eqx.is_array(x))):
            return jax.tree.map(lambda x: jax.device_put(np.asarray(x)[i]) if eqx.is_array(x) else x, self.model)
        return jax.tree.map(lambda x: x[i] if eqx.is_array(x) else x, self.model)

    def status_labels(self) -> list[str]:
        return [FitStatus(int(s)).label for s in np.asarray(self.status)]

    @classmethod
    def placeholder(cls, model0: AbstractKinematicModel, fleet: typing.Any, free: typing.Any = None) -> FitSolution:
        """A solution of the structure, shapes and dtypes that :func:`fit` gives for
        ``fleet`` from ``model0`` with the free set ``free``, holding the start models
        and zeros (status 0): for compiling what consumes a fit before the fit exists
        (see :func:`heliojax._programs.warm_up`). Not a fit: never report it."""
        _, static, args = _prepare(model0, fleet, None, free, None, None, None, None, DEFAULT_MAX_STEPS)
        view, models = static[0], args[0]
        n_records, dtype = int(np.shape(fleet.mask)[1]), fleet.counts.dtype
        # the fields of a heliostat left out of a fit (one definition of them), batched
        shapes = jax.eval_shape(jax.vmap(lambda m: _not_fitted(view, m, n_records, dtype)), models)
        zeros = {k: jax.device_put(np.zeros(x.shape, x.dtype)) for k, x in shapes.items() if k != "model"}
        return cls(model=models, view=view, **zeros)  # device_put: no eager XLA operation


def _fit_one(
    view: ParameterView,
    solver: optx.AbstractLeastSquaresSolver,
    loss: AbstractLoss,
    prior: AbstractPrior,
    max_steps: int,
    model0: AbstractKinematicModel,
    prior_h: typing.Any,
    loss_h: typing.Any,
    geometry: HeliostatGeometry,
    counts: Float[Array, "M 2"],
    context: RecordContext,
    focal: Float[Array, "M 3"],
    mask: Bool[Array, " M"],
) -> dict[str, typing.Any]:
    counts, context, focal, use, bad_input = sanitise(geometry, counts, context, focal, mask)
    dtype = counts.dtype
    n_records = counts.shape[0]
    n_used = jnp.sum(use)
    p0 = view.to_vector(model0)
    idx = jnp.asarray(view.free_index, dtype=jnp.int32)
    free_scales = view.free_scales(dtype)

    def physical(y):
        return p0.at[idx].add(y * free_scales)

    # An unconstrained fit is never reported (TOO_FEW_RECORDS below), so its parameters
    # are held at the start: its rows do not depend on them, and the solve stops at once
    # instead of spending up to max_steps on a problem with more unknowns than equations.
    # Its rows are still those of its records (at the start model), so that the
    # residuals reported come from the solver's last rows for every heliostat.
    n_prior = prior.n_constrained(view, prior_h)
    too_few = (n_used < 1) | (n_used + n_prior.astype(n_used.dtype) < view.n_free)

    def held(y):
        return jnp.where(too_few, jnp.zeros_like(y), y)

    def record_row(y, c, x, f):
        return loss.row(view.from_vector(model0, physical(y)).beam_components(geometry, c, x, f) * 1e3, loss_h)

    def prior_rows(y):
        return prior.rows(view, physical(y), prior_h)

    def rows(y):
        r, pr = record_rows(record_row, held(y), (counts, context, focal), use), prior_rows(held(y))
        return jnp.concatenate([r, pr]) if pr.shape[0] else r

    def residual_and_jacobian(y):
        r, jac = record_rows_and_jacobian(record_row, held(y), (counts, context, focal), use)
        pr = prior_rows(held(y))
        if pr.shape[0]:
            r = jnp.concatenate([r, pr])
            jac = jnp.concatenate([jac, jax.jacfwd(prior_rows)(held(y))])
        return r, jnp.where(too_few, 0.0, jac)

    residual = residual_with_jacobian(rows, residual_and_jacobian)
    out = solve_least_squares(residual, jnp.zeros(view.n_free, dtype), solver, max_steps)
    data_r = out.residual[: 2 * n_records]

    # Gauss-Newton covariance of the free parameters (scaled units -> physical).
    dof = jnp.maximum(2 * n_used - view.n_free, 1)
    sigma2 = jnp.sum(data_r**2) / dof.astype(data_r.dtype)
    # With a prior that constrains the parameters, few records suffice; the noise
    # then comes from the prior (the fleet's) while the heliostat's own residuals
    # have fewer degrees of freedom than parameters.
    prior_noise = prior.noise_mrad_of(prior_h)
    sigma2 = jnp.where((2 * n_used - view.n_free < view.n_free) & (n_prior > 0), prior_noise**2, sigma2)
    normal = out.jacobian.T @ out.jacobian
    a_inv = psd_inverse(normal)
    cov_scaled = a_inv * sigma2
    cov = cov_scaled * free_scales[:, None] * free_scales[None, :]
    undetermined = jnp.diag(normal) <= 0.0
    std_free = jnp.where(undetermined, jnp.nan, jnp.sqrt(jnp.clip(jnp.diag(cov_scaled), 0.0)) * free_scales)
    std = jnp.zeros_like(p0).at[idx].set(std_free)

    params = physical(out.value)
    rms = jnp.sqrt(
        jnp.sum(jnp.where(use[:, None], data_r.reshape(-1, 2) ** 2, 0.0)) / jnp.maximum(n_used, 1).astype(data_r.dtype)
    )

    # An unconstrained fit is never reported: keep the start values where too few records.
    params = jnp.where(too_few, p0, params)
    # the residuals at the solution, read off the solver's last rows (no second model evaluation)
    b = jax.vmap(loss.residual_of_row, (0, None))(data_r.reshape(n_records, 2), loss_h)
    loo = _leave_one_out_mrad(out.jacobian[: 2 * n_records].reshape(n_records, 2, -1), a_inv, b)

    status = status_code(out.result)
    status = jnp.where(jnp.all(jnp.isfinite(params)) & jnp.isfinite(out.cost), status, FitStatus.DIVERGED)
    status = jnp.where(bad_input, FitStatus.NON_FINITE_INPUT, status)
    status = jnp.where(too_few, FitStatus.TOO_FEW_RECORDS, status)
    status = jnp.where(jnp.any(mask), status, FitStatus.NO_RECORDS)
    std = jnp.where(too_few, jnp.nan, std)
    cov = jnp.where(too_few, jnp.nan, cov)
    return dict(
        model=view.from_vector(model0, params),
        std=std,
        covariance=cov,
        status=status.astype(jnp.int32),
        n_steps=jnp.where(too_few, 1, out.n_steps).astype(jnp.int32),  # its records are not fitted
        n_used=n_used.astype(jnp.int32),
        rms_mrad=jnp.where(too_few, jnp.nan, rms),
        # a heliostat with too few records is not fitted: its cost is its prior rows' alone
        cost=jnp.where(too_few, 0.5 * jnp.sum(out.residual[2 * n_records :] ** 2), out.cost),
        noise_mrad=jnp.where(too_few, jnp.nan, jnp.sqrt(sigma2)),
        loo_mrad=jnp.where(use & ~too_few, loo, jnp.nan),
        residual_mrad=jnp.where(use[:, None], b, jnp.nan),
    )


def _not_fitted(view: ParameterView, model0: AbstractKinematicModel, n_records: int, dtype: typing.Any) -> dict:
    """What :func:`_fit_one` returns, for a heliostat left out of a fit: its start model,
    zeros elsewhere (the same structure and dtypes, without tracing the fit again)."""
    p0 = view.to_vector(model0).astype(dtype)
    zero = jnp.zeros((), dtype)
    none = jnp.zeros((), jnp.int32)
    return dict(
        model=view.from_vector(model0, p0),
        std=jnp.zeros_like(p0),
        covariance=jnp.zeros((view.n_free, view.n_free), dtype),
        status=none,
        n_steps=none,
        n_used=none,
        rms_mrad=zero,
        cost=zero,
        noise_mrad=zero,
        loo_mrad=jnp.zeros((n_records,), dtype),
        residual_mrad=jnp.zeros((n_records, 2), dtype),
    )


def _leave_one_out_mrad(jac: Float[Array, "M 2 F"], a_inv: Float[Array, "F F"], b: Float[Array, "M 2"]) -> Array:
    """``(M,)`` ``|(I - H_ii)^-1 b_i|`` with ``H_ii = J_i A^-1 J_i^T`` (2 x 2 per
    record; infinite where the record alone determines a direction, ``det(I - H_ii)``
    ~ 0)."""
    hat = jnp.einsum("mif,fg,mjg->mij", jac, a_inv, jac)
    m = jnp.eye(2, dtype=b.dtype)[None] - hat
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    adj = jnp.stack([jnp.stack([m[:, 1, 1], -m[:, 0, 1]], -1), jnp.stack([-m[:, 1, 0], m[:, 0, 0]], -1)], -2)
    safe = det > 1e-9
    e = jnp.einsum("mij,mj->mi", adj, b) / jnp.where(safe, det, 1.0)[:, None]
    return jnp.where(safe, jnp.linalg.norm(e, axis=-1), jnp.inf)


@program_jit  # the CPU compiles it with XLA's older fusion emitters (heliojax._xla_flags)
def _fit_compiled(
    view,
    solver,
    loss,
    prior,
    max_steps,
    batching,
    model0,
    prior_h,
    loss_h,
    geometry,
    counts,
    context,
    focal,
    mask,
    active,
):
    def one(m, ph, lh, g, c, x, f, k, a):
        def fitted():
            return _fit_one(view, solver, loss, prior, max_steps, m, ph, lh, g, c, x, f, k)

        def not_fitted():  # the start model; the caller takes the rest from an earlier fit
            return _not_fitted(view, m, c.shape[0], c.dtype)

        # a branch, not a select, under lax.map: a heliostat left out costs nothing
        return jax.lax.cond(a, fitted, not_fitted)

    return batching.map(one)(model0, prior_h, loss_h, geometry, counts, context, focal, mask, active)


def fit_mask(mask: typing.Any, shape: tuple[int, ...], who: str = "fit") -> typing.Any:
    """``mask`` checked against the fleet's ``(H, M)``: its shape (also under ``jit``) and
    type; a concrete integer mask of 0 and 1 becomes boolean. A mask of another shape
    had met a broadcasting error naming nothing, a float mask a dtype error of ``&``,
    and an integer mask of counts (2) selected nothing (``2 & True`` is 0)."""
    if mask is None:
        return None
    array = mask if isinstance(mask, jax.Array) else np.asarray(mask)
    if tuple(array.shape) != tuple(shape):
        raise ValueError(
            f"{who}: mask has shape {tuple(array.shape)}; expected {tuple(shape)}, the fleet's (H, M) records"
        )
    if array.dtype == bool:
        return mask
    concrete = not isinstance(array, jax.core.Tracer)  # pyright: ignore[reportAttributeAccessIssue]
    if array.dtype.kind in "iu" and concrete and np.isin(np.asarray(array), (0, 1)).all():
        return jax.device_put(np.asarray(array, bool))
    raise ValueError(
        f"{who}: mask has dtype {array.dtype}{' with values other than 0 and 1' if array.dtype.kind in 'iu' else ''}; "
        "expected booleans (H, M), True for the records to fit"
    )


_FLEET_FIELDS = ("geometry", "counts", "context", "focal_spot", "mask")
"""The fields of a :class:`heliojax.Fleet` that :func:`fit` reads."""


def batched_for(model0: AbstractKinematicModel, h: int, who: str = "fit", name: str = "model0") -> typing.Any:
    """``model0`` batched over ``h`` heliostats: one model broadcast, or a batch of ``h``
    as it is. A batch of models for another fleet size had failed in the batching's scan
    (or a vmap), naming no argument."""
    if not is_batched(model0):
        return broadcast_model(model0, h)
    sizes = {jnp.shape(x)[0] for x in jax.tree.leaves(model0) if eqx.is_array(x) and jnp.ndim(x)}
    if sizes != {h}:
        raise ValueError(
            f"{who}: {name} is batched over {', '.join(map(str, sorted(sizes)))} heliostats and the fleet has {h}; "
            "give one model (used for every heliostat) or one per heliostat of the fleet"
        )
    return model0


def check_fleet(fleet: typing.Any, name: str = "fleet", *, who: str = "fit") -> None:
    """TypeError unless ``fleet`` (the argument ``name`` of ``who``) is a
    :class:`heliojax.Fleet` (or has the fields :func:`fit` reads): None or a path had
    failed as "no attribute 'mask'" (or 'counts', 'ids') inside."""
    if not all(hasattr(fleet, field) for field in _FLEET_FIELDS):
        raise TypeError(
            f"{who}: {name}: expected a heliojax.Fleet (heliojax.load_paint_directory, heliojax.fleet_from_arrays), "
            f"got {type(fleet).__name__}"
        )


def check_kinds(model0, fleet, solver=None, loss=None, prior=None, batching=None, *, who: str = "fit") -> None:
    """TypeError naming the argument of :func:`fit` that is not of its kind: a string
    (``batching="vmap"``, ``loss="cauchy"``), a dict for a prior or a minimiser for the
    solver had failed as an AttributeError inside the fit or optimistix, a fleet of None
    as "no attribute 'mask'", a model0 of a string as "empty model"."""
    if not isinstance(model0, AbstractKinematicModel):
        raise TypeError(
            f"{who}: model0: expected a kinematic model (e.g. heliojax.StoneModel.nominal()), "
            f"got {type(model0).__name__}"
        )
    check_fleet(fleet, who=who)
    for name, value, kind, hint in (
        ("solver", solver, optx.AbstractLeastSquaresSolver, "an optimistix least-squares solver"),
        ("loss", loss, AbstractLoss, "heliojax.fitting.LeastSquares() or heliojax.fitting.Cauchy(scale_mrad)"),
        ("prior", prior, AbstractPrior, "heliojax.gaussian_prior(model, sigma) or heliojax.fitting.fleet_prior"),
        ("batching", batching, AbstractBatching, "e.g. heliojax.LaxMap() or heliojax.fitting.batching_from_name"),
    ):
        if value is not None and not isinstance(value, kind):
            raise TypeError(f"{who}: {name}: expected {hint}, or None for the default; got {type(value).__name__}")


def _prepare(model0, fleet, mask, free, solver, loss, prior, batching, max_steps, active=None):
    if count_problem(max_steps, MAX_FIT_STEPS) is not None:
        raise ValueError(f"max_steps: expected an integer >= 1 and <= {MAX_FIT_STEPS:,}, got {max_steps!r}"[:200])
    check_kinds(model0, fleet, solver, loss, prior, batching)
    h = int(np.shape(fleet.mask)[0])
    dtype = fleet.counts.dtype
    if dtype != np.float64:
        # float32 LM stalls at its tolerances and the covariances break down (an SVD that
        # does not converge, deep inside discovery): say so where the user can act
        raise ConfigError(
            f"the fleet's records are {np.dtype(dtype).name}; calibration needs float64: call "
            'jax.config.update("jax_enable_x64", True) before loading or building the fleet (the heliojax '
            "command does)"
        )
    model0 = jax.tree.map(lambda x: jnp.asarray(x, dtype) if eqx.is_inexact_array(x) else x, model0)
    model0 = batched_for(model0, h)
    mask = fit_mask(mask, np.shape(fleet.mask))
    view = ParameterView.of(model0, free)
    if view.n_free == 0:  # had failed as "integer modulo by zero" deep inside JAX
        raise ValueError("fit: free: no parameter is free; a fit needs at least one (heliojax.default_free(model))")
    solver = default_solver() if solver is None else solver
    loss = LeastSquares() if loss is None else loss
    prior = NoPrior() if prior is None else prior
    if isinstance(prior, GaussianPrior):  # another model's prior had failed as an AttributeError inside the fit
        for name, part in (("centre", prior.centre), ("sigma", prior.sigma)):
            names = ParameterView.of(part).names
            if names != view.names:
                raise ValueError(
                    f"fit: prior: its {name} is a {type(part).__name__} of the parameters {', '.join(names)}; "
                    f"model0 ({type(model0).__name__}) has {', '.join(view.names)}"
                )
    batching = default_batching() if batching is None else batching
    m = fleet.mask if mask is None else and_masks(mask, fleet.mask)
    check_unit_vectors(fleet.context.sun, m, "fleet.context.sun")
    args = (
        model0,
        prior.per_heliostat(h),
        loss.per_heliostat(h),
        fleet.geometry,
        fleet.counts,
        fleet.context,
        fleet.focal_spot,
        m,
        jax.device_put(np.ones((h,), bool) if active is None else np.asarray(active, bool)),  # no eager XLA op
    )
    static = (view, solver, loss, prior, max_steps, batching)
    return h, static, batching.prepare(args)


def fit(
    model0: AbstractKinematicModel,
    fleet: typing.Any,
    *,
    mask: Bool[Array, "H M"] | None = None,
    free: typing.Any = None,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    loss: AbstractLoss | None = None,
    prior: AbstractPrior | None = None,
    batching: AbstractBatching | None = None,
    max_steps: int = DEFAULT_MAX_STEPS,
) -> FitSolution:
    """Fit every heliostat of ``fleet`` in one compiled program.

    Args:
        model0: the start model: one model (used for every heliostat) or models
            batched along a leading axis ``H``; its non-free parameters stay as given.
        fleet: a :class:`heliojax.Fleet` (pad it to a shape bucket with
            :func:`heliojax.pad_fleet` so new fleet sizes reuse the compiled program).
        mask: ``(H, M)`` records to fit (ANDed with ``fleet.mask``).
        free: the free set, a pytree of booleans of ``model0``'s structure
            (default :func:`heliojax.default_free`).
        solver: an optimistix least-squares solver (default :func:`default_solver`).
        loss: :class:`LeastSquares` (default) or a robust loss.
        prior: :class:`NoPrior` (default) or e.g. :class:`GaussianPrior`.
        batching: strategy over heliostats (default :func:`default_batching`).
        max_steps: solver step limit (kept small so one slow lane cannot stall a batch).

    Returns:
        A :class:`FitSolution`.

    Raises:
        TypeError: an argument of another kind (a string for ``batching`` or ``loss``, a
            dict for ``prior``, a minimiser for ``solver``, None for ``fleet``).
        ValueError: a ``mask``, start model, Cauchy scale or prior for another number of
            heliostats or records, a prior of another model, a free set of no parameter.
    """
    h, static, args = _prepare(model0, fleet, mask, free, solver, loss, prior, batching, max_steps)
    out = _fit_in_passes(static, args)
    return FitSolution(view=static[0], **static[-1].finish(out, h))


def _fit_in_passes(static: tuple, args: tuple) -> dict[str, typing.Any]:
    """The compiled fit; with ``Vmap(restart_after=K)``, a first pass of ``K`` steps,
    then the lanes that hit that limit again, gathered into a batch of a power-of-two
    size, with the remaining steps (see :class:`heliojax.Vmap`)."""
    view, solver, loss, prior, max_steps, batching = static
    first = batching.restart_after if isinstance(batching, Vmap) else None
    if first is None or first >= max_steps:
        return batching.run(_fit_compiled, static, args)
    out = _fit_compiled(view, solver, loss, prior, first, batching, *args)
    late = np.flatnonzero(np.asarray(out["status"]) == FitStatus.MAX_STEPS)
    if late.size == 0:
        return out
    size = min(1 << int(late.size - 1).bit_length(), int(np.shape(out["status"])[0]))
    index = jnp.asarray(np.concatenate([late, np.full(size - late.size, late[-1])]))

    def take(x):
        return x[index] if eqx.is_array(x) else x

    again = (jax.tree.map(take, out["model"]), *jax.tree.map(take, args[1:]))
    rest = _fit_compiled(view, solver, loss, prior, max_steps - first, batching, *again)
    rest["n_steps"] = rest["n_steps"] + first
    return jax.tree.map(lambda a, b: a.at[index].set(b) if eqx.is_array(a) else a, out, rest)


class CompiledFit:
    """A fit lowered and compiled ahead of time for one fleet and one set of static
    options, callable again with other start models, losses or priors of the same
    structure (the robust passes reuse the least-squares program this way).

    Attributes:
        compile_s: seconds spent tracing, lowering and compiling.
        batching: the strategy over heliostats it was compiled for (the option, or
            :func:`heliojax.default_batching`).
    """

    def __init__(self, model0: AbstractKinematicModel, fleet: typing.Any, **options: typing.Any):
        self._fleet = fleet
        self._mask = options.pop("mask", None)
        self._options = options
        h, static, args = _prepare(
            model0,
            fleet,
            self._mask,
            options.get("free"),
            options.get("solver"),
            options.get("loss"),
            options.get("prior"),
            options.get("batching"),
            options.get("max_steps", DEFAULT_MAX_STEPS),
        )
        unknown = set(options) - {"free", "solver", "loss", "prior", "batching", "max_steps"}
        if unknown:
            raise TypeError(f"unknown fit options {sorted(unknown)}")
        t0 = time.perf_counter()
        self.batching: AbstractBatching = static[-1]
        self._compiled = compile_cached(_fit_compiled, *static, *self.batching.block(args))
        self.compile_s = time.perf_counter() - t0
        self._h = h
        self.run_s = 0.0

    def __call__(
        self,
        model0: AbstractKinematicModel,
        *,
        loss: AbstractLoss | None = None,
        prior: AbstractPrior | None = None,
        only: Bool[ArrayLike, " H"] | None = None,
        otherwise: FitSolution | None = None,
    ) -> FitSolution:
        """Run the compiled fit from ``model0`` (with ``loss`` / ``prior`` replacing
        the compiled ones; same structure required).

        With ``only`` (``(H,)`` booleans), only those heliostats are fitted; the others'
        results are taken from ``otherwise`` (a :class:`FitSolution` of the same fleet,
        e.g. an earlier pass). Under :class:`heliojax.LaxMap` (the CPU default) a
        heliostat left out costs nothing; batched by :class:`heliojax.Vmap` it is
        computed and discarded."""
        if (only is None) != (otherwise is None):
            raise TypeError("CompiledFit: give `only` and `otherwise` together")
        if only is not None and (np.asarray(only).dtype != bool or np.shape(only) != (self._h,)):
            # indices had been read as booleans, another length failed as XLA's "Argument types
            # differ ... a different enable_x64 mode"
            raise ValueError(
                f"CompiledFit: only must be ({self._h},) booleans, one per heliostat; got "
                f"{np.asarray(only).dtype} of shape {np.shape(only)}"
            )
        if otherwise is not None and not isinstance(otherwise, FitSolution):
            raise TypeError(
                f"CompiledFit: otherwise must be a FitSolution of the fleet, got {type(otherwise).__name__}"
            )
        opts = dict(self._options)
        if loss is not None:
            opts["loss"] = loss
        if prior is not None:
            opts["prior"] = prior
        h, static, args = _prepare(
            model0,
            self._fleet,
            self._mask,
            opts.get("free"),
            opts.get("solver"),
            opts.get("loss"),
            opts.get("prior"),
            opts.get("batching"),
            opts.get("max_steps", DEFAULT_MAX_STEPS),
            only,
        )
        t0 = time.perf_counter()
        out = static[-1].run(self._compiled, static, args)
        jax.block_until_ready(out)
        self.run_s += time.perf_counter() - t0
        solution = FitSolution(view=static[0], **static[-1].finish(out, h))
        if otherwise is None:
            return solution
        return _merge(jax.device_put(np.asarray(only, bool)), solution, otherwise)


@functools.partial(cached_jit, quick=True)  # one program, not an eager XLA operation per field
def _merge(keep: Bool[Array, " H"], new: FitSolution, old: FitSolution) -> FitSolution:
    """``new``'s heliostats where ``keep``, ``old``'s elsewhere."""

    def pick(a, b):
        if not eqx.is_array(a):
            return a
        return jnp.where(keep.reshape(keep.shape + (1,) * (jnp.ndim(a) - 1)), a, b)

    return jax.tree.map(pick, new, old)


def fit_timed(
    model0: AbstractKinematicModel, fleet: typing.Any, **options: typing.Any
) -> tuple[FitSolution, float, float]:
    """:func:`fit` with its compile and run times measured separately (ahead-of-time
    lowering): ``(solution, compile_s, run_s)``."""
    compiled = CompiledFit(model0, fleet, **options)
    solution = compiled(model0)
    return solution, compiled.compile_s, compiled.run_s


__all__ = [
    "CompiledFit",
    "DEFAULT_ATOL",
    "DEFAULT_INITIAL_DAMPING",
    "DEFAULT_MAX_STEPS",
    "DEFAULT_RTOL",
    "FitSolution",
    "LeastSquaresOutcome",
    "default_solver",
    "fit",
    "fit_timed",
    "psd_inverse",
    "record_rows",
    "record_rows_and_jacobian",
    "residual_with_jacobian",
    "solve_least_squares",
    "status_code",
]
