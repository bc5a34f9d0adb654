"""Change points: dates at which a heliostat's axis offsets jumped (maintenance,
re-mounting, an actuator swap).

Around a fit of all of a heliostat's records (residual rows ``r``, Jacobian
``J`` of the free parameters, both weighted by the records' robust weights),
every record time ``t_c`` is a candidate: the linearised least-squares problem
gets two more columns, the Jacobian of the two axis offsets on the records at or
after ``t_c`` (a jump of both offsets from ``t_c`` on). The candidate that lowers
the residual sum of squares most wins; its evidence is that drop in units of the
likelihood ratio with the noise variance profiled out, ``delta_chi2 = n_rows
ln(RSS_0 / RSS_c)`` (``n_rows`` = 2 x the records used), so that it does not
depend on a noise estimate the jump itself inflates. Any change of state counts,
a slow drift of the offsets included (its best step is where it splits the
records best); each change is then labelled a step or a drift: the same
likelihood ratio for a linear drift of the two offsets (two columns, the offsets'
Jacobian times the standardised record time) against none gives
``drift_delta_chi2``, and ``is_step`` says where the Bayesian information
criterion prefers the step (three parameters) to the drift (two). Calibration
acts on every change (the later records describe the heliostat better either
way); discovery only on steps, so that a creeping heliostat or a clock running
off is not split at a false date. Where the records cannot tell the two apart
(two campaigns in time: a step between them and a drift fit alike) the step's
extra fit decides. A change point is reported
where the Bayesian information criterion prefers it: ``delta_chi2 > 3
ln(n_rows)`` (two jumps and the location are three more parameters). For a
clean heliostat the statistic at one candidate is about chi-square with 2
degrees of freedom, so the threshold (14.4 at 60 records) is exceeded with
probability ~exp(-7) per candidate; the scan over candidates multiplies that by
at most their number.
Each segment needs ``min_segment`` records, by default as many as the model has
free parameters (each segment alone determines the model twice over: a short
segment cannot be told from a few noisy records). No constant here was chosen
on the shared records.
"""

from __future__ import annotations

import functools
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._errors import ConfigError
from .._heliostat import known_values
from .._limits import count_problem
from .._parameters import ParameterView, and_masks
from .._programs import cached_jit
from ._evaluate import residual_jacobians, residuals_mrad
from ._fit import FitSolution, check_kinds, fit_mask
from ._records import finite_records

OFFSET_NAMES: tuple[tuple[str, str], ...] = (("angle_offset_1", "angle_offset_2"), ("theta_k", "tau_k"))
"""The axis-offset parameter pairs a jump is sought in (actuator model, Stone model)."""

MAX_SEGMENT = 2**31 - 1
"""Largest ``min_segment`` (records) :func:`find_change_points` takes (its counts are int32)."""


@typing.final
class ChangePoints(eqx.Module):
    """Per heliostat ``(H,)``: the most likely change point and its evidence.

    Attributes:
        found: a change point is reported (``delta_chi2 > threshold``).
        index: record index (into the fleet's ``M`` axis) of the first record at
            or after the change (-1 where no candidate was possible).
        time_s: unix time of that record (s; NaN where none).
        previous_time_s: unix time of the last record before it (s; NaN where none):
            the change happened between the two.
        jump_mrad: ``(H, 2)`` the jump of the two offsets (mrad; later minus earlier).
        delta_chi2: the evidence (see the module docstring).
        threshold: ``3 ln(n_rows)``.
        n_after: records used at or after the change.
        drift_delta_chi2: the evidence of a linear drift of the two offsets against
            none (like ``delta_chi2``; two more parameters).
        is_step: change points that are jumps rather than drifts: those whose step
            the Bayesian information criterion prefers to a linear drift of the two
            offsets (``delta_chi2 - 3 ln n > drift_delta_chi2 - 2 ln n``, i.e.
            ``delta_chi2 - drift_delta_chi2 > threshold / 3``, :attr:`step_margin`).
        offsets: the names of the two offset parameters; static.
    """

    found: Bool[Array, " H"]
    index: Int[Array, " H"]
    time_s: Float[Array, " H"]
    previous_time_s: Float[Array, " H"]
    jump_mrad: Float[Array, "H 2"]
    delta_chi2: Float[Array, " H"]
    threshold: Float[Array, " H"]
    n_after: Int[Array, " H"]
    drift_delta_chi2: Float[Array, " H"]
    is_step: Bool[Array, " H"]
    offsets: tuple[str, str] = eqx.field(static=True)

    @property
    def step_margin(self) -> Float[Array, " H"]:
        """``ln n_rows`` (``threshold / 3``): the Bayesian information criterion's price
        of the step's one parameter more than the drift's, by which the step's evidence
        must exceed the drift's for :attr:`is_step`."""
        return self.threshold / 3.0


def _offset_columns(view: ParameterView) -> tuple[tuple[str, str], list[int]]:
    for pair in OFFSET_NAMES:
        if all(n in view.free_names for n in pair):
            return pair, [view.free_names.index(n) for n in pair]
    raise ConfigError(
        f"change points need a free pair of axis offsets ({' or '.join('/'.join(p) for p in OFFSET_NAMES)}); "
        f"free parameters: {', '.join(view.free_names)}"
    )


def jump_scan(
    base: Float[Array, "M 2 F"],
    jump: Float[Array, "M 2 2"],
    residual: Float[Array, "M 2"],
    time: Float[Array, " M"],
    use: Bool[Array, " M"],
) -> tuple[Float[Array, ""], tuple[Float[Array, "M 2"], Float[Array, " M"]], Int[Array, " M"]]:
    """The linearised change-point problem of one heliostat, for every candidate date at once.

    Each record time ``t_c`` is a candidate: the design ``base`` (rows of the records,
    ``F`` columns) gets the two ``jump`` columns on the records at or after ``t_c``.
    By the Frisch-Waugh-Lovell theorem the jump coefficients are ``C^-1 a`` with
    ``a = E^T r_perp``, ``C = E^T E - E^T B (B^T B)^+ B^T E`` (``E``: the jump columns
    after ``t_c``, ``r_perp``: the residual of the base fit), and the residual sum of
    squares drops by ``a^T C^-1 a``. ``E^T r_perp``, ``E^T E`` and ``E^T B`` are
    suffix sums over the records in time order: O(M F^2) for all candidates, not a
    least-squares solve per candidate (``tests/test_changes.py`` checks it against
    those solves).

    Args:
        base: ``(M, 2, F)`` weighted design rows of the free parameters.
        jump: ``(M, 2, 2)`` weighted rows of the two jump columns (before masking).
        residual: ``(M, 2)`` weighted residual rows.
        time: ``(M,)`` record times (any unit; ``inf`` for unused records; NaN for
            records without a time, which are never after a candidate).
        use: ``(M,)`` records that count.

    Returns:
        ``(rss0, (coef, rss_drop), n_after)``: the base fit's residual sum of squares;
        per candidate the ``(M, 2)`` jump coefficients and the drop of the residual sum
        of squares (0 where the jump columns are degenerate); the used records at or
        after each candidate.
    """
    use_f = use.astype(base.dtype)
    b, e = base * use_f[:, None, None], jump * use_f[:, None, None]
    gram_pinv, r_perp = _project_out(base, residual, use)
    rss0 = jnp.sum(r_perp**2)
    # Records without a time (NaN) are in the base design but never after a candidate:
    # sorted first, so that no suffix of a dated candidate holds them.
    key = jnp.where(jnp.isnan(time), -jnp.inf, time)
    order = jnp.argsort(key)
    t_sorted = key[order]

    def suffix(x):  # sums over the records at or after each sorted position, then 0
        x = x[order]
        total = jnp.cumsum(x[::-1], axis=0)[::-1]
        return jnp.concatenate([total, jnp.zeros((1,) + x.shape[1:], x.dtype)], axis=0)

    # ties: all records of t_c count as after; an undated candidate has none after it
    first = jnp.where(jnp.isnan(time), time.shape[0], jnp.searchsorted(t_sorted, key, side="left"))
    er = suffix(jnp.einsum("mij,mi->mj", e, r_perp))[first]  # (M, 2)
    ee = suffix(jnp.einsum("mij,mik->mjk", e, e))[first]  # (M, 2, 2)
    eb = suffix(jnp.einsum("mij,mif->mjf", e, b))[first]  # (M, 2, F)
    n_after = suffix(use.astype(jnp.int32))[first]
    c = ee - jnp.einsum("mjf,fg,mkg->mjk", eb, gram_pinv, eb)
    det = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
    # Degenerate where the projected jump Gram is tiny against the jump columns' own
    # Gram: judged against ``C`` itself, rounding noise in a ``C`` that should be 0 (a
    # jump inside the base's span) would pass as proper.
    size = jnp.maximum(ee[:, 0, 0] + ee[:, 1, 1], jnp.finfo(base.dtype).tiny)
    proper = det > 1e-12 * size**2
    safe_det = jnp.where(proper, det, 1.0)
    inv = jnp.stack([jnp.stack([c[:, 1, 1], -c[:, 0, 1]], -1), jnp.stack([-c[:, 1, 0], c[:, 0, 0]], -1)], -2)
    coef = jnp.where(proper[:, None], jnp.einsum("mjk,mk->mj", inv, er) / safe_det[:, None], 0.0)
    drop = jnp.where(proper, jnp.sum(er * coef, axis=-1), 0.0)
    return rss0, (coef, drop), n_after


def drift_coordinate(unix_time: Float[Array, " M"], use: Bool[Array, " M"]) -> Float[Array, " M"]:
    """``(t - mean) / std`` over the used, dated records (dimensionless; 0 for the others
    and where all dated records share one time): the coordinate of a linear drift."""
    dated = use & jnp.isfinite(unix_time)
    n = jnp.maximum(jnp.sum(dated), 1).astype(unix_time.dtype)
    t = jnp.where(dated, unix_time, 0.0)
    mean = jnp.sum(t) / n
    d = jnp.where(dated, unix_time - mean, 0.0)
    std = jnp.sqrt(jnp.sum(d**2) / n)
    return jnp.where(std > 0, d / jnp.where(std > 0, std, 1.0), 0.0)


def _project_out(
    design: Float[Array, "M 2 F"], residual: Float[Array, "M 2"], use: Bool[Array, " M"]
) -> tuple[Float[Array, "F F"], Float[Array, "M 2"]]:
    """``(G^+, r_perp)``: the pseudo-inverse of the used rows' Gram matrix of ``design``
    and the used rows of ``residual`` after least squares in ``design`` (unused rows 0)."""
    u = use.astype(design.dtype)
    b, r = design * u[:, None, None], residual * u[:, None]
    gram_pinv = jnp.linalg.pinv(jnp.einsum("mif,mig->fg", b, b), hermitian=True)
    return gram_pinv, r - jnp.einsum("mif,f->mi", b, gram_pinv @ jnp.einsum("mif,mi->f", b, r))


@functools.partial(cached_jit, quick=True)  # traced once per machine when the CLI keeps programs
def _scan(columns, min_segment, residual, jacobian, counts, context, focal, mask, weight):
    def one(residual, jacobian, counts, context, focal, mask, weight):
        use = mask & finite_records(counts, context, focal)
        sw = jnp.sqrt(jnp.where(use, jnp.clip(weight, 0.0, 1.0), 0.0))
        r = jnp.where(use[:, None], residual, 0.0) * sw[:, None]  # (M, 2) mrad; a non-finite fit stays NaN
        jac = jacobian * sw[:, None, None]  # (M, 2, F) mrad / physical unit
        scale = jnp.maximum(jnp.sqrt(jnp.sum(jac**2, axis=(0, 1))), 1e-30)  # column scaling for conditioning
        jac = jac / scale[None, None, :]
        jump_cols = jac[:, :, jnp.asarray(columns)]  # (M, 2, 2)
        drift_cols = jump_cols * drift_coordinate(context.unix_time, use)[:, None, None]
        with_drift = jnp.concatenate([jac, drift_cols], axis=-1)
        t = jnp.where(use, context.unix_time, jnp.inf)
        rss0, (coef, drop), n_after = jump_scan(jac, jump_cols, r, t, use)
        ok = (n_after >= min_segment) & (jnp.sum(use).astype(jnp.int32) - n_after >= min_segment)
        gain = jnp.where(ok & jnp.isfinite(rss0) & jnp.isfinite(drop), drop, -jnp.inf)  # NaN rows: no candidate
        jump = -coef / scale[None, jnp.asarray(columns)] * 1e3  # rows are residuals: the offsets move the other way
        best = jnp.argmax(gain)
        possible = jnp.isfinite(gain[best])
        n_rows = 2 * jnp.sum(use)
        threshold = 3.0 * jnp.log(jnp.maximum(n_rows, 2).astype(r.dtype))
        rss1 = jnp.maximum(rss0 - gain[best], 1e-300)
        dchi2 = jnp.where(possible, n_rows.astype(r.dtype) * jnp.log(jnp.maximum(rss0, 1e-300) / rss1), jnp.nan)
        t_best = t[best]
        before = jnp.where(use & (t < t_best), t, -jnp.inf)
        rss_drift = jnp.sum(_project_out(with_drift, r, use)[1] ** 2)
        drift_dchi2 = n_rows.astype(r.dtype) * jnp.log(jnp.maximum(rss0, 1e-300) / jnp.maximum(rss_drift, 1e-300))
        found = possible & (dchi2 > threshold)
        return dict(
            found=found,
            index=jnp.where(possible, best, -1).astype(jnp.int32),
            time_s=jnp.where(possible, t_best, jnp.nan),
            previous_time_s=jnp.where(possible, jnp.max(before), jnp.nan),
            jump_mrad=jnp.where(possible, jump[best], jnp.nan),
            delta_chi2=dchi2,
            threshold=threshold,
            n_after=jnp.where(possible, n_after[best], 0).astype(jnp.int32),
            drift_delta_chi2=jnp.where(jnp.isfinite(drift_dchi2), drift_dchi2, jnp.nan),
            is_step=found & (dchi2 - drift_dchi2 > threshold / 3.0),
        )

    return jax.vmap(one)(residual, jacobian, counts, context, focal, mask, weight)


def find_change_points(
    solution: FitSolution,
    fleet: typing.Any,
    mask: Bool[Array, "H M"],
    weights: Float[Array, "H M"],
    *,
    min_segment: int | None = None,
) -> ChangePoints:
    """The most likely jump of the axis offsets per heliostat (see the module docstring).

    Args:
        solution: a fit of ``fleet`` (its models are the linearisation point).
        fleet: the :class:`heliojax.Fleet` that was fitted.
        mask: ``(H, M)`` the records the fit used (e.g. the training records).
        weights: ``(H, M)`` robust record weights (1 for least squares; 0 ignores a record).
        min_segment: records each side of a change point at least (default: the
            number of free parameters).

    Raises:
        ConfigError: the model has no free pair of axis offsets.
        TypeError, ValueError: a ``solution`` of another fleet, a ``mask`` or ``weights``
            of another shape, ``weights`` not finite and >= 0, or a ``min_segment`` that
            is not a whole number >= 1 (a change point with no record on one side had
            been scanned for, 2.5 read as 2, NaN weights had found nothing without a word).
    """
    if not isinstance(solution, FitSolution):
        raise TypeError(f"find_change_points: solution: expected a FitSolution, got {type(solution).__name__}")
    check_kinds(solution.model, fleet, who="find_change_points")
    shape = tuple(np.shape(fleet.mask))
    if solution.n_heliostats != shape[0]:  # had failed in a vmap naming JAX's argument names
        raise ValueError(
            f"find_change_points: solution holds {solution.n_heliostats} heliostats and the fleet {shape[0]}; "
            "give the fleet that was fitted"
        )
    mask = fit_mask(mask, shape, "find_change_points")
    if tuple(np.shape(weights)) != shape:
        raise ValueError(f"find_change_points: weights has shape {np.shape(weights)}; expected {shape}, the fleet's")
    w = known_values(weights)
    if w is not None and not np.all(np.isfinite(w) & (w >= 0)):
        raise ValueError(
            "find_change_points: weights must be finite and >= 0 (1 for least squares, 0 ignores a record)"
        )
    problem = None if min_segment is None else count_problem(min_segment, MAX_SEGMENT)
    if problem is not None:
        raise ValueError(f"find_change_points: min_segment {problem}")
    names, columns = _offset_columns(solution.view)
    use = and_masks(mask, fleet.mask)
    # the residuals and their Jacobian come from the programs the drift and planning use too,
    # so the scan itself compiles only the linear algebra below
    args = (fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, use)
    out = _scan(
        tuple(columns),
        int(solution.view.n_free if min_segment is None else min_segment),
        residuals_mrad(solution.model, *args),
        residual_jacobians(solution.model, solution.view, *args),
        fleet.counts,
        fleet.context,
        fleet.focal_spot,
        use,
        jnp.asarray(weights, fleet.counts.dtype),
    )
    return ChangePoints(offsets=names, **out)
