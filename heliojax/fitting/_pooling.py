"""Fleet pooling: an empirical-Bayes prior learnt from the fleet's own parameters.

A heliostat with few records cannot determine its parameters alone, but the
fleet tells what values are typical. :func:`fleet_prior` learns, per parameter,
a Gaussian ``N(centre, spread^2)`` from the *well-determined* heliostats of a fit
(converged, with at least three residuals per free parameter):

* ``centre``: the median of their fitted values;
* ``spread^2``: the robust variance of their fitted values (1.4826 MAD)^2 minus
  the median squared standard error (method of moments, robust in both terms: what
  remains is the spread of the true values), floored at
  ``(SPREAD_FLOOR_SCALED * scale)^2`` so that no parameter is pinned harder than
  1/10 of its solver scale (0.1 mrad for angles, 1e-3 for ratios) by a fleet that
  happens to agree, plus the centre's own sampling variance
  ``pi/2 (1.4826 MAD)^2 / n`` (the variance of a median of ``n`` values): a prior
  learnt from a few heliostats, or from heliostats whose fitted values scatter
  widely, is weak, not a tight prior at an uncertain centre. (With the mean squared
  standard error and no centre term, a fleet whose half was broken, or whose
  heliostats were mostly weakly determined, got a prior floored at 0.1 mrad around
  a contaminated centre, and its good heliostats were pulled off their data.)

Refitting every heliostat with this prior (:func:`heliojax.fitting.fit_robust`
with ``pool=True``) calibrates heliostats with a handful of records; for a
heliostat with many records the prior rows are weak against its data (its
standard errors are far below the fleet spread), so it is not pulled measurably.

A fleet in which fewer than :data:`MIN_PRIOR_HELIOSTATS` heliostats determine their
parameters alone cannot teach a median and a MAD. There the heliostats that do not
determine theirs get a **small-fleet prior** instead (:func:`small_fleet_prior_moments`):
centred on the mean of the one or two heliostats that do (the nominal values when
none does), its spread the larger of their sample spread (two heliostats) and the
typical size each parameter's model declares (:func:`heliojax.parameter`'s
``typical``: 1 mrad for the tilts, 10 mrad for the joint offsets, 1 % for the gear
ratios and increment scales, 1 mm for the stroke offsets; written with the models,
not learnt from any records), widened by the centre's own variance (that of a mean
of ``n``). Real plants share large systematic parameters (the Jülich heliostats'
``beta`` and ``delta`` lie near -12 and +11 mrad in every heliostat), which the
nominal values miss and even one well-determined heliostat shows. The heliostats
that determine their parameters alone keep no prior (they are not pulled).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._kinematics import AbstractKinematicModel
from .._limits import MAX_SYNTHETIC_HELIOSTATS, count_problem
from .._parameters import ParameterView, broadcast_model, is_batched
from ._fit import FitSolution
from ._prior import GaussianPrior
from ._status import FitStatus

SPREAD_FLOOR_SCALED = 0.1
"""Smallest prior spread, in units of each parameter's solver scale."""

MIN_PRIOR_HELIOSTATS = 3
"""Fewest well-determined heliostats a fleet prior is learnt from (a median and a MAD
need three); with fewer the prior constrains nothing."""

MIN_RESIDUALS_PER_PARAMETER = 3
"""A heliostat is well determined with at least this many residuals per free parameter."""


def flat_prior(model: AbstractKinematicModel, n: int, noise_mrad: float = 1.0) -> GaussianPrior:
    """A prior of the pooled structure that constrains nothing (``sigma = inf``):
    fits with it run the same compiled program as fits with a learnt prior."""
    problem = count_problem(n, MAX_SYNTHETIC_HELIOSTATS)  # 0 had made a prior of no heliostat, 2.5 a NumPy error
    if problem is not None:
        raise ValueError(f"flat_prior: n {problem}")
    models = model if is_batched(model) else broadcast_model(model, n)
    view = ParameterView.of(models)
    inf = jax.device_put(np.full((n, view.n_parameters), np.inf, jnp.asarray(view.to_vector(models)).dtype))
    sigma = _from_vectors(view, models, inf)
    noise = jax.device_put(np.full((n,), noise_mrad, inf.dtype))  # no eager XLA op
    return GaussianPrior(centre=models, sigma=sigma, noise_mrad=noise)


def _from_vectors(view: ParameterView, models: AbstractKinematicModel, vectors: Float[Array, "H P"]):
    return view._from_vectors(models, vectors)


def well_determined(solution: FitSolution) -> np.ndarray:
    """``(H,)`` heliostats whose fit the fleet prior may learn from."""
    status = np.asarray(solution.status)
    n_res = 2 * np.asarray(solution.n_used)
    finite = np.all(np.isfinite(np.asarray(solution.std)), axis=1)
    return (status == FitStatus.CONVERGED) & (n_res >= MIN_RESIDUALS_PER_PARAMETER * solution.view.n_free) & finite


def prior_moments(
    view: ParameterView,
    params: Float[np.ndarray, "H P"],
    std: Float[np.ndarray, "H P"],
    learn_from: Bool[np.ndarray, " H"],
    fallback_centre: Float[np.ndarray, " P"],
) -> tuple[Float[np.ndarray, " P"], Float[np.ndarray, " P"]]:
    """Centre and spread (physical units, vector order of ``view``) of the fleet
    prior learnt from the heliostats ``learn_from`` (see the module docstring).
    With fewer than :data:`MIN_PRIOR_HELIOSTATS` of them the centre is ``fallback_centre`` and every
    spread ``inf``; non-free parameters have spread ``inf``."""
    p = np.asarray(params, float)
    scales = np.asarray(view.scales)
    free = np.asarray(view.free)
    centre = np.asarray(fallback_centre, float).copy()
    spread = np.full(p.shape[1], np.inf)
    good = np.asarray(learn_from, bool)
    if good.sum() >= MIN_PRIOR_HELIOSTATS:
        pg, sg = p[good], np.asarray(std, float)[good]
        med = np.median(pg, axis=0)
        mad_var = (1.4826 * np.median(np.abs(pg - med), axis=0)) ** 2
        var = mad_var - np.median(sg**2, axis=0)
        floor = (SPREAD_FLOOR_SCALED * scales) ** 2
        centre_var = np.pi / 2 * mad_var / good.sum()  # the median centre's own sampling variance
        centre = np.where(free, med, centre)
        spread = np.where(free, np.sqrt(np.maximum(var, floor) + centre_var), np.inf)
    return centre, spread


def small_fleet_prior_moments(
    view: ParameterView,
    params: Float[np.ndarray, "H P"],
    std: Float[np.ndarray, "H P"],
    learn_from: Bool[np.ndarray, " H"],
) -> tuple[Float[np.ndarray, " P"], Float[np.ndarray, " P"]]:
    """Centre and spread (physical units, vector order of ``view``) of the prior for a
    fleet with fewer than :data:`MIN_PRIOR_HELIOSTATS` heliostats ``learn_from`` (see the
    module docstring): centre the mean of their fitted values (the nominal values
    without any); spread ``sqrt(v (1 + 1/n))`` over ``n`` of them (``v`` without any),
    ``v`` the larger of the declared typical size squared and their sample variance
    minus their median squared standard error (two heliostats); ``inf`` where no
    typical size is declared and for parameters that are not free."""
    free = np.asarray(view.free, bool)
    typical = np.array([np.inf if t is None else t for t in view.typical], float)
    good = np.asarray(learn_from, bool)
    n = int(good.sum())
    centre = np.asarray(view.nominal, float)
    var = typical**2
    if n:
        p = np.asarray(params, float)[good]
        centre = p.mean(axis=0)
        if n >= 2:
            se2 = np.median(np.asarray(std, float)[good] ** 2, axis=0)
            var = np.maximum(var, p.var(axis=0, ddof=1) - np.where(np.isfinite(se2), se2, 0.0))
    spread = np.sqrt(var * (1.0 + 1.0 / n)) if n else np.sqrt(var)
    return np.where(free, centre, np.asarray(view.nominal, float)), np.where(free, spread, np.inf)


def small_fleet_prior_heliostats(solution: FitSolution, learn_from: Bool[ArrayLike, " H"] | None = None) -> np.ndarray:
    """``(H,)`` the heliostats :func:`fleet_prior` (not leave-one-out, small-fleet
    fallback on) gives the small-fleet prior: all that are not :func:`well_determined`
    when fewer than :data:`MIN_PRIOR_HELIOSTATS` heliostats are there to learn from
    (``learn_from``, default :func:`well_determined`), else none."""
    alone = well_determined(solution)
    good = alone if learn_from is None else np.asarray(learn_from, bool)
    return ~alone if int(good.sum()) < MIN_PRIOR_HELIOSTATS else np.zeros_like(alone)


def fleet_prior(
    solution: FitSolution,
    noise_mrad: Float[Array, " H"],
    learn_from: Bool[Array, " H"] | None = None,
    *,
    leave_one_out: bool = False,
    small_fleet_fallback: bool = True,
) -> GaussianPrior:
    """The fleet's empirical-Bayes prior (see the module docstring) for every
    heliostat of ``solution``.

    Args:
        solution: a fit of the fleet (e.g. the robust fit).
        noise_mrad: ``(H,)`` noise per residual component that scales the prior rows.
        learn_from: heliostats to learn from (default :func:`well_determined`).
        leave_one_out: each heliostat's prior learnt from the *other* heliostats
            (what the fleet knows before this heliostat has a record: retrospective
            studies; ``O(H^2)`` work, for studies rather than plant-size fleets).
        small_fleet_fallback: where no prior can be learnt (fewer than
            :data:`MIN_PRIOR_HELIOSTATS` heliostats to learn from), the heliostats that
            are not :func:`well_determined` get the small-fleet prior
            (:func:`small_fleet_prior_moments`; see the module docstring); ``False``:
            none (e.g. when ``noise_mrad`` is no noise estimate: no heliostat converged).

    Returns:
        A :class:`GaussianPrior` batched over the heliostats (centre and spread the
        same for all unless ``leave_one_out`` or the small-fleet fallback, noise per
        heliostat).
    """
    view = solution.view
    p = np.asarray(solution.parameters())
    h = p.shape[0]
    # integer indices had been read as booleans (index 0 dropped, the rest taken), another
    # length failed in NumPy's indexing, a noise per heliostat of another length in the fit
    if learn_from is not None and (np.asarray(learn_from).dtype != bool or np.shape(learn_from) != (h,)):
        raise ValueError(
            f"fleet_prior: learn_from must be ({h},) booleans, one per heliostat of the solution; got "
            f"{np.asarray(learn_from).dtype} of shape {np.shape(learn_from)}"
        )
    if np.ndim(noise_mrad) not in (0, 1) or np.ndim(noise_mrad) == 1 and np.shape(noise_mrad) != (h,):
        raise ValueError(f"fleet_prior: noise_mrad has shape {np.shape(noise_mrad)}; expected () or ({h},)")
    good = well_determined(solution) if learn_from is None else np.asarray(learn_from, bool)
    fallback = np.asarray(view.to_vector(solution.heliostat_model(0)), float)
    std = np.asarray(solution.std)
    if leave_one_out:
        pairs = [prior_moments(view, p, std, good & (np.arange(h) != i), fallback) for i in range(h)]
        centres = np.stack([c for c, _ in pairs])
        spreads = np.stack([s for _, s in pairs])
    else:
        centre, spread = prior_moments(view, p, std, good, fallback)
        centres = np.broadcast_to(centre, (h, centre.size))
        spreads = np.broadcast_to(spread, (h, spread.size))
    if small_fleet_fallback and leave_one_out:
        free = np.asarray(view.free, bool)
        small = ~np.isfinite(spreads[:, free]).any(axis=1) & ~well_determined(solution)  # no fleet prior learnt
        centres, spreads = np.array(centres), np.array(spreads)
        for i in np.flatnonzero(small):  # each from the others, as above (a study's O(H^2) anyway)
            centres[i], spreads[i] = small_fleet_prior_moments(view, p, std, good & (np.arange(h) != i))
    elif small_fleet_fallback:
        small = small_fleet_prior_heliostats(solution, good)
        if small.any():
            small_centre, small_spread = small_fleet_prior_moments(view, p, std, good)
            centres = np.where(small[:, None], small_centre, centres)
            spreads = np.where(small[:, None], small_spread, spreads)
    models = solution.model
    dtype = jax.dtypes.canonicalize_dtype(p.dtype)
    return GaussianPrior(
        centre=_from_vectors(view, models, jax.device_put(np.asarray(centres, dtype))),
        sigma=_from_vectors(view, models, jax.device_put(np.asarray(spreads, dtype))),
        noise_mrad=jnp.asarray(noise_mrad, dtype),
    )


__all__ = [
    "MIN_PRIOR_HELIOSTATS",
    "MIN_RESIDUALS_PER_PARAMETER",
    "SPREAD_FLOOR_SCALED",
    "small_fleet_prior_heliostats",
    "small_fleet_prior_moments",
    "fleet_prior",
    "flat_prior",
    "prior_moments",
    "well_determined",
]
