"""The predicted pointing-error distribution of a calibrated heliostat.

A record (or a command) ``dt`` days after the heliostat's last fitted record has a
2-D residual ``r`` (mrad, the beam's two tangent components) predicted as a
bivariate Student t centred on zero with scale matrix ``S + q dt I`` and
``tail_dof`` degrees of freedom: ``S = J C J^T + noise^2 I`` from the fit
(:func:`heliojax.residual_prediction`), ``q`` (mrad^2 per day per component) a
random-walk drift. ``tail_dof = inf`` is the Gaussian ``N(0, S + q dt I)``.

The t is the Gaussian scale mixture that real records need: maintenance episodes,
gross errors and effects the model lacks make the held-out errors of real
heliostats heavier-tailed than a Gaussian (README, "Predictive uncertainty"). With
``d^2 = r^T (S + q dt I)^-1 r``, ``P(d^2 <= x) = 1 - (1 + x / nu)^(-nu / 2)``
(``d^2 / 2`` follows an F(2, nu) law), which tends to the chi-square(2)
``1 - exp(-x / 2)`` as ``nu -> inf``.

A t cannot describe a mostly Gaussian sample with a few gross errors: the low
``nu`` that the far records need widens its core too. The other law fitted is the
two-component Gaussian scale mixture ``(1 - e) N(0, S') + e N(0, k^2 S')``
(``e``: :attr:`PointingErrorLaw.outlier_fraction`, ``k``:
:attr:`PointingErrorLaw.outlier_scale`), ``P(d^2 <= x) = (1 - e)(1 - exp(-x / 2)) +
e (1 - exp(-x / 2 k^2))``. Real validation residuals can hold three scales (a core,
a shoulder of moderately larger errors, gross errors far out: the shared PAINT
records' median ``d^2`` is twice a Gaussian's while more than 10 % of them lie
beyond 18 times the scale), which neither describes: the third law is the same
mixture of two t's, ``(1 - e) t_nu(S') + e t_nu(k^2 S')``, ``P(d^2 <= x) = (1 - e)
T(x) + e T(x / k^2)`` with ``T`` the t's law above (the Gaussian mixture as ``nu ->
inf``, the t as ``e -> 0``). :func:`fit_drift_and_law` fits all three by maximum
likelihood and keeps the one with the lowest Bayesian information criterion. The law
is one :class:`PointingErrorLaw`.

A model that is not exact also errs more where the heliostat points in poses unlike
the fitted ones: the scale may grow with the *sky gap* ``gap``, the angle (deg) from
the sun of the record (or command) to the nearest sun of the heliostat's fitted
records (:func:`heliojax.sky_gap_deg`), as ``S + (q dt + g gap) I``: a random walk in
time and one across the sky, both with a linear variogram. ``g`` (mrad^2 per degree
per component) is fitted beside ``q`` and the law and kept only where the BIC asks
for it (:func:`fit_drift_gap_and_law`); ``g = 0`` is the law above.

A beam that *creeps* (settling, a joint zero that drifts at a steady rate) errs as
``rho b``, ``b`` the days from the mean time of the fitted records
(:func:`heliojax.days_from_fitted_mean`: a least-squares fit pins the state at that
time), so its variance grows as ``b^2``, faster than a random walk's ``dt``: the
scale ``S + (q dt + g gap + c b^2) I``, ``c`` (mrad^2 per day^2 per component, the
square of a creep rate) fitted beside the walk or instead of it (the validation
records, a few months after the fit, hardly tell the two apart, and they extrapolate
differently: :func:`fit_drift_terms_and_law`).
"""

from __future__ import annotations

import collections.abc
import math
import numbers
import typing

import equinox as eqx
import numpy as np
from jaxtyping import Float

from ._limits import real_problem

_DRIFT_GRID = np.concatenate([[0.0], np.geomspace(1e-6, 1e3, 91)])  # mrad^2 / day
MIN_TAIL_DOF = 0.5
"""The smallest Student t degrees of freedom of a pointing-error law: the fit's grid
starts there (below it a region's radius overflows a float: a 95 % radius of
``nu (0.05^(-2/nu) - 1)`` is 1e260 at ``nu = 1e-3``)."""
_DOF_GRID = np.concatenate([np.geomspace(MIN_TAIL_DOF, 1e3, 67), [np.inf]])
_FRACTION_GRID = np.geomspace(0.003, 0.5, 24)
_SCALE_GRID = np.geomspace(1.5, 1e3, 29)
_GAP_GRID = np.concatenate([[0.0], np.geomspace(1e-5, 1e2, 71)])  # mrad^2 / deg
_CREEP_GRID = np.concatenate([[0.0], np.geomspace(1e-10, 1e1, 111)])  # mrad^2 / day^2


_LAW_KEYS = ("kind", "tail_dof", "outlier_fraction", "outlier_scale")
"""The keys of :meth:`PointingErrorLaw.to_dict` (``kind`` follows from the others)."""


def _law_number(value: typing.Any) -> float:
    """A field of :class:`PointingErrorLaw` as a float: one real number. ``float`` had
    read the string "inf" and True (1 degree of freedom) and failed on None ("float()
    argument must be ...", naming no field)."""
    kind = "U" if isinstance(value, (str, bytes)) else np.asarray(value).dtype.kind
    if kind not in "iuf" or np.ndim(value) != 0:
        raise TypeError(
            "PointingErrorLaw: tail_dof, outlier_fraction and outlier_scale must be numbers "
            f"(tail_dof inf: a Gaussian core), got {value!r}"[:200]
        )
    return float(value)


@typing.final
class PointingErrorLaw(eqx.Module):
    """Radial law of the predicted 2-D pointing error, a Gaussian scale mixture
    (module docstring): a Student t (``tail_dof`` finite), a two-component Gaussian
    mixture (``outlier_fraction > 0``), a mixture of two t's (both) or the Gaussian
    (neither).

    Attributes:
        tail_dof: degrees of freedom of the t; ``inf``: a Gaussian core.
        outlier_fraction: ``e``, the share of the broad component (0: none).
        outlier_scale: ``k``, the broad component's scale over the core's (>= 1).
    """

    tail_dof: float = eqx.field(static=True, default=math.inf, converter=_law_number)
    outlier_fraction: float = eqx.field(static=True, default=0.0, converter=_law_number)
    outlier_scale: float = eqx.field(static=True, default=1.0, converter=_law_number)

    def __check_init__(self):
        if not self.tail_dof >= MIN_TAIL_DOF:
            raise ValueError(f"tail_dof must be at least {MIN_TAIL_DOF} (inf: Gaussian); got {self.tail_dof}")
        if not 0.0 <= self.outlier_fraction < 1.0:
            raise ValueError(f"outlier_fraction must be in [0, 1); got {self.outlier_fraction}")
        if not (math.isfinite(self.outlier_scale) and self.outlier_scale >= 1.0):
            raise ValueError(f"outlier_scale must be finite and >= 1; got {self.outlier_scale}")

    @property
    def kind(self) -> str:
        """``"gaussian"``, ``"student_t"``, ``"gaussian_mixture"`` or ``"student_t_mixture"``."""
        if math.isfinite(self.tail_dof):
            return "student_t_mixture" if self.outlier_fraction > 0.0 else "student_t"
        return "gaussian_mixture" if self.outlier_fraction > 0.0 else "gaussian"

    def cdf(self, d2: Float[np.ndarray, "*n"]) -> Float[np.ndarray, "*n"]:
        """``P(d^2 <= x)`` at ``x = d2`` (squared Mahalanobis radius in the scale)."""
        x = np.maximum(np.asarray(d2, float), 0.0)
        e, k = self.outlier_fraction, self.outlier_scale
        return np.asarray((1.0 - e) * self._core_cdf(x) + e * self._core_cdf(x / (k * k)))

    def _core_cdf(self, x: Float[np.ndarray, "*n"] | np.floating) -> Float[np.ndarray, "*n"] | np.floating:
        """``P(d^2 <= x)`` of one component: the t's (the chi-square(2)'s for ``nu = inf``)."""
        if math.isfinite(self.tail_dof):
            return -np.expm1(-self.tail_dof / 2.0 * np.log1p(x / self.tail_dof))
        return -np.expm1(-x / 2.0)

    def _core_quantile(self, probability: float) -> float:
        """The quantile of :meth:`_core_cdf` (closed form)."""
        if math.isfinite(self.tail_dof):
            return self.tail_dof * math.expm1(-2.0 / self.tail_dof * math.log1p(-probability))
        return -2.0 * math.log1p(-probability)

    def region_d2(self, probability: float) -> float:
        """The squared Mahalanobis radius ``x`` with ``P(d^2 <= x) = probability``
        (closed form for the Gaussian and the t, bisection for the mixtures).

        Raises:
            ValueError: ``probability`` outside (0, 1).
        """
        if real_problem(probability) is not None or not 0.0 < probability < 1.0:  # "0.95" or an array had failed
            raise ValueError(f"probability must be in (0, 1); got {probability!r}"[:200])
        if self.outlier_fraction == 0.0:
            return self._core_quantile(probability)
        # between the core's and the broad component's own quantiles; bisection in log x
        lo = self._core_quantile(probability)
        hi = lo * self.outlier_scale**2
        for _ in range(200):
            mid = math.sqrt(lo) * math.sqrt(hi)  # lo * hi had underflowed to 0 at p = 1e-300 (a ZeroDivisionError)
            lo, hi = (mid, hi) if float(self.cdf(np.asarray(mid))) < probability else (lo, mid)
            if hi / lo < 1.0 + 1e-13:
                break
        return math.sqrt(lo) * math.sqrt(hi)

    def describe(self) -> str:
        """A short name for titles and logs."""
        core = f"Student t, {self.tail_dof:.2g} degrees of freedom" if math.isfinite(self.tail_dof) else "Gaussian"
        if self.outlier_fraction > 0.0:
            return f"{core} + {100 * self.outlier_fraction:.2g} % at {self.outlier_scale:.3g}x scale"
        return core

    @classmethod
    def from_dict(cls, data: collections.abc.Mapping[str, typing.Any] | None) -> PointingErrorLaw:
        """Inverse of :meth:`to_dict` (``None`` or missing keys: the Gaussian's values).

        Raises:
            TypeError: ``data`` is not a mapping (a list raised AttributeError), or a
                value is not a number (``tail_dof`` may be None: a Gaussian core).
            ValueError: a key :meth:`to_dict` does not write (a misspelt one was
                read as the Gaussian's value), or a value out of its range.
        """
        if data is None:
            data = {}
        if not isinstance(data, collections.abc.Mapping):
            raise TypeError(
                "PointingErrorLaw.from_dict: data: expected a mapping of tail_dof, outlier_fraction and "
                f"outlier_scale (PointingErrorLaw.to_dict) or None, got {type(data).__name__}"
            )
        unknown = sorted(str(k) for k in data if k not in _LAW_KEYS)
        if unknown:
            raise ValueError(f"PointingErrorLaw.from_dict: data: unknown keys {unknown} (expected {list(_LAW_KEYS)})")
        values = {}
        for key, default in (("tail_dof", None), ("outlier_fraction", 0.0), ("outlier_scale", 1.0)):
            value = data.get(key, default)
            if value is None and key == "tail_dof":
                value = math.inf
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise TypeError(f"PointingErrorLaw.from_dict: data[{key!r}]: expected a number, got {value!r}"[:200])
            values[key] = float(value)
        return cls(**values)

    def to_dict(self) -> dict[str, typing.Any]:
        """JSON form (``tail_dof`` null for a Gaussian core)."""
        return {
            "kind": self.kind,
            "tail_dof": None if math.isinf(self.tail_dof) else self.tail_dof,
            "outlier_fraction": self.outlier_fraction,
            "outlier_scale": self.outlier_scale,
        }


def prediction_region_d2(probability: float, law: PointingErrorLaw | float = math.inf) -> float:
    """The squared Mahalanobis radius ``x`` with ``P(d^2 <= x) = probability`` of the
    predicted 2-D pointing error (see the module docstring) under ``law`` (a
    :class:`PointingErrorLaw`, or a number: the t's degrees of freedom, ``inf`` the
    Gaussian): ``-2 ln(1 - p)`` for a Gaussian (5.991 at 95 %),
    ``nu ((1 - p)^(-2 / nu) - 1)`` for a Student t with ``nu`` degrees of freedom.

    Raises:
        ValueError: ``probability`` outside (0, 1) or a degrees of freedom not positive.
    """
    if not isinstance(law, PointingErrorLaw):
        law = PointingErrorLaw(tail_dof=law)
    return law.region_d2(probability)


def region_radius(largest_scale_eigenvalue, probability: float, law: PointingErrorLaw | float = math.inf):
    """Radius (the scale's units' square root, mrad) of the circle that holds the
    predicted error with at least ``probability``: the region's semi-major axis
    ``sqrt(prediction_region_d2(probability, law) * largest eigenvalue)``. Works on
    NumPy and JAX arrays alike."""
    return (prediction_region_d2(probability, law) * largest_scale_eigenvalue) ** 0.5


def _kernel(d2: Float[np.ndarray, "*#n"], dof: float | Float[np.ndarray, "*#n"]) -> Float[np.ndarray, "..."]:
    """Log-density of a bivariate t with ``dof`` degrees of freedom (``inf``: Gaussian;
    or an array of finite ones, broadcast against ``d2``) at squared Mahalanobis radius
    ``d2``, less ``log 2 pi`` and half the scale's log determinant (the t's normalising
    constant in 2-D does not depend on ``dof``)."""
    if np.ndim(dof) == 0 and math.isinf(dof):
        return -0.5 * d2
    return -(dof / 2.0 + 1.0) * np.log1p(d2 / dof)


def _log_likelihood(
    d2: Float[np.ndarray, "*#v Q N"], logdet: Float[np.ndarray, "*#v Q N"], dof: float | Float[np.ndarray, "*#v 1 1"]
) -> Float[np.ndarray, "..."]:
    """Summed log-likelihood (less ``N log 2 pi``) of bivariate t residuals with
    ``dof`` degrees of freedom (``inf``: Gaussian; or finite ones along leading axes)
    for each drift (rows)."""
    return np.sum(_kernel(d2, dof) - 0.5 * logdet, axis=-1)


def _grid(
    residual_mrad: Float[np.ndarray, "N 2"],
    scale_mrad2: Float[np.ndarray, "N 2 2"],
    days: Float[np.ndarray, " N"] | None,
    extra_mrad2: Float[np.ndarray, " N"] | None = None,
) -> tuple[Float[np.ndarray, "Q N"], Float[np.ndarray, "Q N"]]:
    """``d^2`` and ``ln det`` of every residual under its scale plus each drift of the
    grid (plus ``extra_mrad2``, per component), in closed form for 2 x 2 matrices;
    ``days`` None: no drift, one row (``Q = 1``, the drift 0)."""
    r = np.asarray(residual_mrad, float)
    s = np.asarray(scale_mrad2, float)
    if days is None:
        c = np.zeros((1, r.shape[0]))
    else:
        c = _DRIFT_GRID[:, None] * np.asarray(days, float)[None, :]
    if extra_mrad2 is not None:
        c = c + np.asarray(extra_mrad2, float)[None, :]
    a, d = s[:, 0, 0] + c, s[:, 1, 1] + c
    b = 0.5 * (s[:, 0, 1] + s[:, 1, 0])
    det = a * d - b * b
    d2 = (d * r[:, 0] ** 2 - 2.0 * b * r[:, 0] * r[:, 1] + a * r[:, 1] ** 2) / det
    return d2, np.log(det)


def _best_t(
    d2: Float[np.ndarray, "Q N"], logdet: Float[np.ndarray, "Q N"], dofs: Float[np.ndarray, " V"] = _DOF_GRID
) -> tuple[int, float, float]:
    """``(drift index, tail_dof, log-likelihood)`` of the most likely t (Gaussian
    included) among the degrees of freedom ``dofs`` (ascending, ``inf`` last)."""
    ll = _t_log_likelihoods(d2, logdet, dofs)  # (Q, V)
    # the last index of the maximum: among equally likely values, the Gaussian and the smallest drift
    iq, iv = np.unravel_index(np.argmax(ll[:, ::-1]), ll.shape)
    return int(iq), float(dofs[::-1][iv]), float(ll[iq, ll.shape[1] - 1 - iv])


_BLOCK_ELEMENTS = 1 << 21
"""Largest ``(V, Q, N)`` block of t log-densities :func:`_t_log_likelihoods` evaluates
at once (16 MiB of float64)."""


def _t_log_likelihoods(
    d2: Float[np.ndarray, "Q N"], logdet: Float[np.ndarray, "Q N"], dofs: Float[np.ndarray, " V"]
) -> Float[np.ndarray, "Q V"]:
    """:func:`_log_likelihood` for every drift (rows) and degrees of freedom ``dofs``
    (columns; ``inf``: Gaussian), the finite ones in blocks of at most
    :data:`_BLOCK_ELEMENTS` log-densities (one numpy call per block, not per ``nu``;
    the same values, summed in the same order)."""
    dofs = np.asarray(dofs, float)
    out = np.empty((d2.shape[0], dofs.size))
    finite = np.flatnonzero(np.isfinite(dofs))
    step = max(1, _BLOCK_ELEMENTS // max(d2.size, 1))
    for start in range(0, finite.size, step):
        columns = finite[start : start + step]
        out[:, columns] = _log_likelihood(d2[None], logdet[None], dofs[columns][:, None, None]).T
    for column in np.flatnonzero(~np.isfinite(dofs)):
        out[:, column] = _log_likelihood(d2, logdet, math.inf)
    return out


_PROFILE_DOFS = np.append(_DOF_GRID[:-1][::3], np.inf)
"""Every third degrees of freedom of the t's grid and the Gaussian: the sky-gap profile's."""


def fit_drift_and_tails(
    residual_mrad: Float[np.ndarray, "N 2"],
    scale_mrad2: Float[np.ndarray, "N 2 2"],
    days: Float[np.ndarray, " N"],
) -> tuple[float, float]:
    """Maximum-likelihood drift ``q`` (mrad^2/day per component) and ``tail_dof`` of
    the predicted distribution (module docstring) from validation residuals with
    their fitted scale ``S`` and days since the fit.

    The likelihood is maximised on a grid: ``q`` in 0 and 1e-6-1e3 (ratio 1.26),
    ``tail_dof`` in 0.5-1000 (ratio 1.12) and ``inf``; a Gaussian fit to Gaussian
    residuals is chosen over ``tail_dof = 1000`` whenever it is at least as likely.

    Returns:
        ``(q, tail_dof)``.
    """
    iq, dof, _ = _best_t(*_grid(*_validation_arrays(residual_mrad, scale_mrad2, days)))
    return float(_DRIFT_GRID[iq]), dof


def fit_drift_and_law(
    residual_mrad: Float[np.ndarray, "N 2"],
    scale_mrad2: Float[np.ndarray, "N 2 2"],
    days: Float[np.ndarray, " N"],
) -> tuple[float, PointingErrorLaw]:
    """Maximum-likelihood drift ``q`` (mrad^2/day per component) and the error law
    (module docstring) from validation residuals with their fitted scale ``S`` and
    days since the fit: the Student t family (as :func:`fit_drift_and_tails`, the
    Gaussian included), the two-component Gaussian mixture (``e`` in 0.003-0.5, ``k``
    in 1.5-1000, ratio ~1.25 each, on the same ``q`` grid) and the mixture of two t's
    (every third ``nu`` of the t's grid, the same ``e`` and ``k``, at the drifts of
    the other two families' optima; then ``q`` again on its whole grid), the one with
    the lowest Bayesian information criterion kept (``-2 ln L + p ln N``; ``p`` = 1
    for the Gaussian, 2 for the t, 3 for the Gaussian mixture, 4 for the t mixture).

    Returns:
        ``(q, law)``.

    Raises:
        ValueError: inputs of other shapes, not finite, or days < 0
            (:func:`_validation_arrays`).
    """
    _, iq, law = _fit_law(*_grid(*_validation_arrays(residual_mrad, scale_mrad2, days)))
    return float(_DRIFT_GRID[iq]), law


def _validation_arrays(
    residual_mrad: typing.Any, scale_mrad2: typing.Any, days: typing.Any
) -> tuple[Float[np.ndarray, "N 2"], Float[np.ndarray, "N 2 2"], Float[np.ndarray, " N"]]:
    """The validation records of the drift and law fits as float arrays, checked:
    ValueError naming the argument for a shape other than ``(N, 2)``, ``(N, 2, 2)``,
    ``(N,)``, a value that is not finite, days < 0, no residual at all, or a scale that
    is not symmetric positive definite. One NaN residual had made every
    likelihood NaN and the fit return ``q = 0`` and a Gaussian, without a word; the
    caller (:func:`heliojax.temporal_drift`) leaves out the records it cannot use."""
    r = np.asarray(residual_mrad, float)
    s = np.asarray(scale_mrad2, float)
    t = np.asarray(days, float)
    if r.ndim != 2 or r.shape[1] != 2:
        raise ValueError(f"residual_mrad has shape {r.shape}; expected (N, 2) (east, north) mrad")
    n = r.shape[0]
    if s.shape != (n, 2, 2):
        raise ValueError(f"scale_mrad2 has shape {s.shape}; expected ({n}, 2, 2), one per residual")
    if t.shape != (n,):
        raise ValueError(f"days has shape {t.shape}; expected ({n},), one per residual")
    for name, x in (("residual_mrad", r), ("scale_mrad2", s)):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name}: {int(np.sum(~np.isfinite(x)))} value(s) not finite; leave those records out")
    if not np.all(np.isfinite(t) & (t >= 0.0)):
        raise ValueError("days must be finite and >= 0 (days since the fit), one per residual")
    if n == 0:  # had returned q = 0 and a Gaussian, a law of no residual
        raise ValueError("residual_mrad: no residual; a drift and a law need validation residuals")
    a, b, c, d = s[:, 0, 0], s[:, 0, 1], s[:, 1, 0], s[:, 1, 1]
    # a scale that is no covariance had been read (its upper triangle only) into a t law, with
    # NumPy's warnings of log and sqrt of negative numbers
    asymmetric = np.abs(b - c) > 1e-9 * np.maximum(np.abs(a), np.abs(d))
    bad = asymmetric | ~(a > 0) | ~(a * d - b * c > 0)
    if bad.any():
        raise ValueError(
            f"scale_mrad2: {int(bad.sum())} matrix(es) not symmetric positive definite (the first: residual "
            f"{int(np.argmax(bad))}); expected covariances, mrad^2"
        )
    return r, s, t


def fit_drift_gap_and_law(
    residual_mrad: Float[np.ndarray, "N 2"],
    scale_mrad2: Float[np.ndarray, "N 2 2"],
    days: Float[np.ndarray, " N"],
    sky_gap_deg: Float[np.ndarray, " N"],
) -> tuple[float, float, PointingErrorLaw]:
    """:func:`fit_drift_and_law` with the sky-gap term (module docstring): maximum
    likelihood drift ``q`` (mrad^2/day per component), sky-gap rate ``g`` (mrad^2 per
    degree of sky gap per component) and error law of validation residuals predicted
    with scale ``S + (q dt + g gap) I``.

    ``g`` is chosen by the profile likelihood of the Student t family (every third
    ``nu`` of its grid and the Gaussian; the t keeps gross errors from inflating ``g``)
    on a grid of 0 and 1e-5-100 (ratio 2); the law and ``q`` are fitted at that ``g``,
    then ``q`` on its grid and ``g`` on the fine grid's (ratio 1.26) values within a
    coarse step of it refined, with that law fixed. ``g > 0`` is kept only when its
    BIC (one parameter more) is lower than that of :func:`fit_drift_and_law`'s result;
    ties go to the smaller ``g``.

    Args:
        residual_mrad: ``(N, 2)`` validation residuals, mrad.
        scale_mrad2: ``(N, 2, 2)`` their fitted scale ``S``, mrad^2.
        days: ``(N,)`` days since the fit.
        sky_gap_deg: ``(N,)`` angle (deg) from each record's sun to the nearest sun of
            the records the fit used, finite and >= 0.

    Returns:
        ``(q, g, law)``.

    Raises:
        ValueError: a sky gap that is not finite or negative, or of another length, and
            the other inputs as in :func:`fit_drift_and_law`.
    """
    q, rates, law = fit_drift_terms_and_law(residual_mrad, scale_mrad2, days, sky_gap_deg=sky_gap_deg)
    return q, rates["sky_gap_deg"], law


DRIFT_TERMS = {"sky_gap_deg": _GAP_GRID, "creep_days2": _CREEP_GRID}
"""The variance terms :func:`fit_drift_terms_and_law` may add to the drift, in the
order it tries them, with their rate grids: ``sky_gap_deg`` (rate ``g``, mrad^2 per
degree of sky gap) and ``creep_days2`` (rate ``c``, mrad^2 per day^2, the square of
the days from the fitted records' mean time, :func:`heliojax.days_from_fitted_mean`)."""

DRIFT_RATE_KEYS = {"sky_gap_deg": "sky_gap_mrad2_per_deg", "creep_days2": "creep_mrad2_per_day2"}
"""The key of each drift term's rate in the predictive entry
(:func:`heliojax.temporal_drift`, ``summary.json``) and in ``results.h5``'s attributes."""

_WALK_ALTERNATIVES = frozenset({"creep_days2"})
"""The terms of :data:`DRIFT_TERMS` also tried *instead of* the random walk: laws of
the same drift in time that the validation span can hardly tell from the walk, and
that extrapolate differently (``dt^2`` against ``dt``)."""


def fit_drift_terms_and_law(
    residual_mrad: Float[np.ndarray, "N 2"],
    scale_mrad2: Float[np.ndarray, "N 2 2"],
    days: Float[np.ndarray, " N"],
    **covariates: Float[np.ndarray, " N"],
) -> tuple[float, dict[str, float], PointingErrorLaw]:
    """:func:`fit_drift_and_law` with variance terms (module docstring): maximum
    likelihood drift ``q`` (mrad^2/day per component), a rate per term and the error
    law of validation residuals predicted with scale ``S + (q dt + sum_k rate_k x_k)
    I``, ``x_k`` the term's covariate (:data:`DRIFT_TERMS`: ``sky_gap_deg``, the sky
    gap in deg; ``creep_days2``, the squared days from the fitted records' mean time).

    Forward selection, in :data:`DRIFT_TERMS`' order: a term's rate is chosen by the
    profile likelihood of the Student t family (every third ``nu`` of its grid and
    the Gaussian; the t keeps gross errors from inflating it) on every third value of
    its grid with the terms kept so far fixed; the law and ``q`` are fitted at that
    rate, then ``q`` on its grid and the rate on its grid's values within a coarse
    step of it refined, with that law fixed. The term is kept only when its BIC (one
    parameter more) is lower than that of the terms kept before it; ties go to the
    smaller rate. The creep is tried twice, beside the random walk and instead of it
    (``q = 0``, as many parameters as before it).

    Args:
        residual_mrad: ``(N, 2)`` validation residuals, mrad.
        scale_mrad2: ``(N, 2, 2)`` their fitted scale ``S``, mrad^2.
        days: ``(N,)`` days since the fit (:func:`heliojax.days_since_fit`).
        **covariates: ``(N,)`` finite values >= 0 of the terms to try, by name.

    Returns:
        ``(q, rates, law)``, ``rates`` one per covariate given (0: not kept).

    Raises:
        ValueError: an unknown term, a covariate that is not finite, negative or of
            another length, and the other inputs as in :func:`fit_drift_and_law`.
    """
    r, s, days = _validation_arrays(residual_mrad, scale_mrad2, days)
    terms = {}
    for name, x in covariates.items():
        if name not in DRIFT_TERMS:
            raise ValueError(f"unknown drift term {name!r}; expected one of {sorted(DRIFT_TERMS)}")
        x = np.asarray(x, float)
        if x.shape != r.shape[:1] or not np.all(np.isfinite(x) & (x >= 0.0)):
            raise ValueError(f"{name} must hold {r.shape[0]} finite values >= 0, one per residual")
        terms[name] = x
    penalty = math.log(max(r.shape[0], 1))
    bic, iq, law = _fit_law(*_grid(r, s, days))
    rates = dict.fromkeys(covariates, 0.0)
    extra = np.zeros(r.shape[0])
    walk: np.ndarray | None = days  # the random walk's days; None once the creep has replaced it
    for name in (n for n in DRIFT_TERMS if n in terms):
        x, grid = terms[name], DRIFT_TERMS[name]
        kept = sum(v > 0.0 for v in rates.values())
        # beside the random walk (one parameter more); an alternative to the walk also
        # instead of it (as many parameters)
        variants = [(walk, kept + 1)] + ([(None, kept)] if name in _WALK_ALTERNATIVES and walk is not None else [])
        for walk_k, extra_parameters in variants:
            coarse = grid[::3]
            profile = [_best_t(*_grid(r, s, walk_k, extra + v * x), _PROFILE_DOFS)[2] for v in coarse]
            ic = int(np.argmax(profile))  # the first maximum: the smallest rate
            if ic == 0:
                continue
            _, _, law_k = _fit_law(*_grid(r, s, walk_k, extra + coarse[ic] * x))
            fine = np.arange(max(3 * ic - 2, 1), min(3 * ic + 3, grid.size))  # the coarse step's neighbours
            ll = np.stack([_law_log_likelihood(*_grid(r, s, walk_k, extra + grid[i] * x), law_k) for i in fine])
            ig, iq_k = np.unravel_index(int(np.argmax(ll)), ll.shape)  # the first maximum: the smallest rate, then q
            bic_k = -2.0 * float(ll[ig, iq_k]) + (_LAW_PARAMETERS[law_k.kind] + extra_parameters) * penalty
            if not bic_k < bic:
                continue
            rates[name] = float(grid[fine[ig]])
            bic, iq, law, walk = bic_k, int(iq_k), law_k, walk_k
        extra = extra + rates[name] * x
    return float(_DRIFT_GRID[iq]) if walk is not None else 0.0, rates, law


_LAW_PARAMETERS = {"gaussian": 1, "student_t": 2, "gaussian_mixture": 3, "student_t_mixture": 4}
"""Parameters of each law's family in the BIC, the drift ``q`` included (:func:`_fit_law`)."""


def _fit_law(d2: Float[np.ndarray, "Q N"], logdet: Float[np.ndarray, "Q N"]) -> tuple[float, int, PointingErrorLaw]:
    """``(bic, drift index, law)`` of the family with the lowest BIC
    (:func:`fit_drift_and_law`) from ``d^2`` and ``ln det`` on the drift grid."""
    penalty = math.log(max(d2.shape[1], 1))
    iq_t, dof, ll_t = _best_t(d2, logdet)
    t_law = PointingErrorLaw(tail_dof=dof)
    candidates = [(-2.0 * ll_t + _LAW_PARAMETERS[t_law.kind] * penalty, iq_t, t_law)]
    k = _SCALE_GRID[:, None, None]
    shift, core, broad = _mixture_parts(_kernel(d2, math.inf), _kernel(d2 / (k * k), math.inf), k)
    base = np.sum(shift - 0.5 * logdet, axis=-1)  # (K, Q)
    best = (math.inf, 0, 0.0, 1.0)
    for e in _FRACTION_GRID:  # every scale and drift at once, (K, Q)
        ll = base + np.sum(np.log((1.0 - e) * core + e * broad), axis=-1)
        ik, iq = np.unravel_index(np.argmax(ll), ll.shape)
        bic = -2.0 * float(ll[ik, iq]) + _LAW_PARAMETERS["gaussian_mixture"] * penalty
        if bic < best[0]:
            best = (bic, int(iq), float(e), float(_SCALE_GRID[ik]))
    candidates.append((best[0], best[1], PointingErrorLaw(outlier_fraction=best[2], outlier_scale=best[3])))
    candidates.append(_best_t_mixture(d2, logdet, sorted({iq_t, best[1]}), penalty))
    return min(candidates, key=lambda c: c[0])


def _law_log_likelihood(
    d2: Float[np.ndarray, "*q N"], logdet: Float[np.ndarray, "*q N"], law: PointingErrorLaw
) -> Float[np.ndarray, "*q"]:
    """Summed log-likelihood (less ``N log 2 pi``) of residuals under ``law``."""
    if law.outlier_fraction == 0.0:
        return _log_likelihood(d2, logdet, law.tail_dof)
    return _t_mixture_log_likelihood(d2, logdet, law.tail_dof, law.outlier_fraction, law.outlier_scale)


def _mixture_parts(
    core: Float[np.ndarray, "..."], broad: Float[np.ndarray, "..."], k: Float[np.ndarray, "..."] | float
) -> tuple[Float[np.ndarray, "..."], Float[np.ndarray, "..."], Float[np.ndarray, "..."]]:
    """``(shift, a, b)`` with :func:`_mixture_log_density` ``= shift + log((1 - e) a +
    e b)`` for every fraction ``e`` (shapes broadcast as there): the two components'
    densities scaled by the larger of them, so that one of ``a``, ``b`` is 1 and the
    logarithm stays finite however far out a record lies. A grid over ``e`` then costs
    one logarithm per record and ``e`` instead of a ``logaddexp``."""
    scaled_broad = broad - 2.0 * np.log(k)
    shift = np.maximum(core, scaled_broad)
    return shift, np.exp(core - shift), np.exp(scaled_broad - shift)


def _mixture_log_density(
    core: Float[np.ndarray, "..."],
    broad: Float[np.ndarray, "..."],
    e: Float[np.ndarray, "..."] | float,
    k: Float[np.ndarray, "..."] | float,
) -> Float[np.ndarray, "..."]:
    """Per-record log-density of ``(1 - e) t_nu(S) + e t_nu(k^2 S)`` (``nu = inf``: two
    Gaussians), less ``log 2 pi`` and half the scale's log determinant, from its two
    components' kernels (:func:`_kernel` at ``d2`` and at ``d2 / k^2``; shapes
    broadcast, e.g. ``broad`` and ``k`` with a leading axis of scales, ``e`` one of
    fractions before it)."""
    return np.logaddexp(np.log1p(-e) + core, np.log(e) - 2.0 * np.log(k) + broad)


def _t_mixture_log_likelihood(
    d2: Float[np.ndarray, "*q N"], logdet: Float[np.ndarray, "*q N"], dof: float, e: float, k: float
) -> Float[np.ndarray, "*q"]:
    """Summed log-likelihood (less ``N log 2 pi``) of ``(1 - e) t_nu(S) + e t_nu(k^2 S)``."""
    both = _mixture_log_density(_kernel(d2, dof), _kernel(d2 / (k * k), dof), e, k)
    return np.sum(both - 0.5 * logdet, axis=-1)


def _best_t_mixture(
    d2: Float[np.ndarray, "Q N"], logdet: Float[np.ndarray, "Q N"], drifts: list[int], penalty: float
) -> tuple[float, int, PointingErrorLaw]:
    """``(bic, drift index, law)`` of the most likely mixture of two t's: ``nu``, ``e``
    and ``k`` on their grids at the drifts ``drifts`` (indices), then the drift on its
    whole grid with those three fixed."""
    k = _SCALE_GRID[:, None]
    e = _FRACTION_GRID[:, None, None]
    found = (-math.inf, 0, 1.0, 0.0, 1.0)  # (log-likelihood, drift index, nu, e, k)
    for iq in drifts:
        x, ld = d2[iq][None, :], logdet[iq][None, :]
        for dof in _DOF_GRID[:-1][::3]:
            shift, core, broad = _mixture_parts(_kernel(x, float(dof)), _kernel(x / (k * k), float(dof)), k)
            # (E, K), every e at once
            ll = np.sum(shift - 0.5 * ld, axis=-1) + np.sum(np.log((1.0 - e) * core + e * broad), axis=-1)
            ie, ik = np.unravel_index(int(np.argmax(ll)), ll.shape)  # the first maximum: the smallest e, then k
            if ll[ie, ik] > found[0]:
                found = (float(ll[ie, ik]), iq, float(dof), float(_FRACTION_GRID[ie]), float(_SCALE_GRID[ik]))
    _, _, dof, e, scale = found
    ll_q = _t_mixture_log_likelihood(d2, logdet, dof, e, scale)
    iq = int(ll_q.shape[0] - 1 - np.argmax(ll_q[::-1]))  # among equally likely drifts, the smallest
    law = PointingErrorLaw(tail_dof=dof, outlier_fraction=e, outlier_scale=scale)
    return -2.0 * float(ll_q[iq]) + _LAW_PARAMETERS[law.kind] * penalty, iq, law


__all__ = [
    "PointingErrorLaw",
    "fit_drift_and_law",
    "fit_drift_and_tails",
    "fit_drift_gap_and_law",
    "fit_drift_terms_and_law",
    "DRIFT_TERMS",
    "prediction_region_d2",
    "region_radius",
]
