"""Level-1 test: sampled mean and standard deviation of a parameter against the
contract values, each with its confidence interval.

Pass rule (``sense`` says which direction is *better* for the plant owner):

* mean, ``sense="lower"`` (tracking, slope error): pass when the lower end of the
  CI of the sampled mean is ``<=`` the contract mean (the sample does not show
  the field to be worse than contracted);
* mean, ``sense="higher"`` (reflectance, aperture): pass when the upper end of
  the CI is ``>=`` the contract mean;
* mean, ``sense="two-sided"``: pass when the contract mean lies inside the CI;
* std (if the contract gives one): pass when the lower end of the CI of the
  sampled std is ``<=`` the contract std (spread not significantly larger);
* and the sample must be at least the required size.

Non-normal parameters. Tracking and slope errors are 2-D radial errors, whose
per-heliostat values follow Rayleigh / Weibull-like, right-skewed, positive
distributions. For them (``distribution="radial"``) the confidence intervals of
mean and std come from a bias-corrected and accelerated (BCa) bootstrap instead
of the normal-theory t / chi-square intervals, and the result also carries a
two-parameter Weibull fit (shape, scale), the 95th percentile and a
Shapiro-Wilk normality p-value, so that a skewed field is visible in the report
rather than hidden behind mean and sd.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Literal

import numpy as np
from jaxtyping import Float
from scipy import stats

Sense = Literal["lower", "higher", "two-sided"]
Distribution = Literal["normal", "radial"]


@dataclasses.dataclass(frozen=True)
class Level1Result:
    """Outcome of :func:`level1_test` for one parameter (all values in the
    parameter's unit).

    Attributes:
        n: number of measured heliostats.
        n_required: sample size required by the contract (0 if not given).
        mean, std: sample mean and standard deviation (ddof=1).
        mean_ci, std_ci: two-sided confidence intervals ``(low, high)``.
        contract_mean, contract_std: contract values (``contract_std`` may be None).
        pass_mean, pass_std, sufficient_sample: the three parts of the verdict.
        passed: all three.
        method: ``"bootstrap-bca"``, ``"bootstrap-percentile"`` (more than
            :data:`BCA_MAX_VALUES` values) or ``"normal"``.
        p95: 95th percentile of the sample.
        weibull_shape, weibull_scale: two-parameter Weibull fit (radial
            parameters only; NaN otherwise). Rayleigh is shape 2.
        normality_p: Shapiro-Wilk p-value (D'Agostino-Pearson beyond 5000 values; NaN for n < 3).
    """

    n: int
    n_required: int
    mean: float
    std: float
    mean_ci: tuple[float, float]
    std_ci: tuple[float, float]
    contract_mean: float
    contract_std: float | None
    pass_mean: bool
    pass_std: bool
    sufficient_sample: bool
    passed: bool
    method: str
    p95: float
    weibull_shape: float
    weibull_scale: float
    normality_p: float

    def to_json(self) -> dict:
        """JSON-ready dict (the ``level1`` entry of ``acceptance.json``)."""
        d = dataclasses.asdict(self)
        d["pass"] = d.pop("passed")
        d["mean_ci"] = list(self.mean_ci)
        d["std_ci"] = list(self.std_ci)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}


BCA_MAX_VALUES = 5000
"""Most values for a BCa bootstrap interval (its jackknife needs memory growing as n^2);
larger samples get the percentile interval."""


def _check_confidence(function: str, confidence: object) -> float:
    """``confidence`` as a float in (0, 1), or ValueError naming it (95 for 95 % had
    given NaN intervals, and a level-1 test failed without a word of why)."""
    if isinstance(confidence, bool) or not isinstance(confidence, int | float | np.integer | np.floating):
        raise TypeError(f"{function}: confidence must be a number in (0, 1), got {confidence!r}")
    if not 0.0 < float(confidence) < 1.0:
        hint = f" (for {confidence:g} %, give {float(confidence) / 100:g})" if 50.0 <= float(confidence) < 100.0 else ""
        raise ValueError(f"{function}: confidence must lie in (0, 1), got {confidence!r}{hint}")
    return float(confidence)


def _check_resamples(function: str, n_resamples: object) -> int:
    if isinstance(n_resamples, bool) or not isinstance(n_resamples, int | np.integer) or n_resamples < 1:
        raise ValueError(f"{function}: n_resamples must be an integer >= 1, got {n_resamples!r}")
    return int(n_resamples)


def confidence_intervals(
    values: Float[np.ndarray, " n"],
    confidence: float = 0.95,
    method: Literal["normal", "bootstrap"] = "normal",
    *,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Two-sided confidence intervals of the mean and of the standard deviation.

    ``"normal"``: Student-t interval of the mean, chi-square interval of the std.
    ``"bootstrap"``: BCa bootstrap (``scipy.stats.bootstrap``) of both, which
    does not assume normality (used for Rayleigh/Weibull-like radial errors).

    Returns:
        ``((mean_low, mean_high), (std_low, std_high))``.

    Raises:
        ValueError: fewer than two values, a NaN or infinite value, ``confidence``
            outside (0, 1), ``n_resamples`` below 1 (bootstrap).
    """
    confidence = _check_confidence("confidence_intervals", confidence)
    if method == "bootstrap":
        n_resamples = _check_resamples("confidence_intervals", n_resamples)
    x = np.asarray(values, dtype=float)
    n = x.size
    if n < 2:
        raise ValueError("need at least two values for a confidence interval")
    if not np.isfinite(x).all():  # NaN intervals (normal) or a failure inside SciPy (bootstrap)
        raise ValueError(
            f"confidence_intervals: {int((~np.isfinite(x)).sum())} of {n} values are NaN or infinite; "
            "drop unmeasured values first (level1_test does)"
        )
    m, s = float(x.mean()), float(x.std(ddof=1))
    alpha = 1.0 - confidence
    if method == "normal":
        half = stats.t.ppf(1 - alpha / 2, n - 1) * s / math.sqrt(n)
        lo = math.sqrt((n - 1) * s**2 / stats.chi2.ppf(1 - alpha / 2, n - 1))
        hi = math.sqrt((n - 1) * s**2 / stats.chi2.ppf(alpha / 2, n - 1))
        return (float(m - half), float(m + half)), (lo, hi)
    if method != "bootstrap":
        raise ValueError(f"method must be 'normal' or 'bootstrap', got {method!r}")
    if s == 0.0:
        return (m, m), (0.0, 0.0)
    rng = np.random.default_rng(seed)
    out = []
    for stat in (np.mean, lambda a, axis: np.std(a, axis=axis, ddof=1)):

        def interval(method: str, stat=stat) -> tuple[float, float]:
            with warnings.catch_warnings():
                # a degenerate BCa (few or tied values) warns and gives NaN: handled below
                warnings.simplefilter("ignore", RuntimeWarning)
                warnings.simplefilter("ignore", getattr(stats, "DegenerateDataWarning", RuntimeWarning))
                res = stats.bootstrap(
                    (x,),
                    stat,
                    confidence_level=confidence,
                    n_resamples=n_resamples,
                    method=method,  # pyright: ignore[reportArgumentType]
                    vectorized=True,
                    axis=-1,
                    random_state=rng,  # pyright: ignore[reportCallIssue]
                )
            return float(res.confidence_interval.low), float(res.confidence_interval.high)

        # BCa's jackknife holds n x (n - 1) values: beyond BCA_MAX_VALUES the percentile
        # interval (BCa's corrections shrink as 1 / sqrt(n))
        lo, hi = interval("BCa") if n <= BCA_MAX_VALUES else (math.nan, math.nan)
        if not (math.isfinite(lo) and math.isfinite(hi)):  # degenerate BCa: percentile
            lo, hi = interval("percentile")
        out.append((lo, hi))
    return out[0], out[1]


def level1_test(
    values: Float[np.ndarray, " n"],
    contract_mean: float,
    contract_std: float | None = None,
    *,
    n_required: int = 0,
    confidence: float = 0.95,
    sense: Sense = "lower",
    distribution: Distribution = "normal",
    n_resamples: int = 2000,
    seed: int = 0,
) -> Level1Result:
    """Compare the sampled mean and std of one parameter with the contract.

    Args:
        values: ``(n,)`` measured values of the sampled heliostats (NaNs dropped).
        contract_mean: contracted field mean (same unit).
        contract_std: contracted standard deviation, or None (then only the mean
            is tested).
        n_required: sample size the contract requires (from :func:`sample_size`).
        confidence: two-sided confidence level of the intervals.
        sense: which direction is better (see the module docstring).
        distribution: ``"radial"`` for 2-D radial errors (bootstrap CIs and a
            Weibull fit), ``"normal"`` for approximately normal parameters.
        n_resamples, seed: bootstrap settings.

    Returns:
        A :class:`Level1Result`.

    Raises:
        ValueError: fewer than two finite values; ``confidence`` outside (0, 1); a
            ``contract_mean`` that is not finite, a ``contract_std`` that is not finite
            and >= 0; ``n_required`` not an integer >= 0; ``n_resamples`` below 1.
            (A NaN contract value or a confidence of 95 had given a failed test and no
            reason.)
    """
    confidence = _check_confidence("level1_test", confidence)
    if distribution == "radial":
        n_resamples = _check_resamples("level1_test", n_resamples)
    for name, value in (("contract_mean", contract_mean), ("contract_std", contract_std)):
        if name == "contract_std" and value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
            raise TypeError(f"level1_test: {name} must be a number, got {value!r}")
        if not math.isfinite(value) or (name == "contract_std" and value < 0):
            bound = "finite and >= 0" if name == "contract_std" else "finite"
            raise ValueError(f"level1_test: {name} must be {bound}, got {value!r}")
    if isinstance(n_required, bool) or not isinstance(n_required, int | np.integer) or n_required < 0:
        raise ValueError(f"level1_test: n_required must be an integer >= 0, got {n_required!r}")
    x = np.asarray(values, dtype=float)
    x = x[np.isfinite(x)]
    if x.size < 2:
        raise ValueError(f"level-1 test needs at least 2 measured values, got {x.size}")
    if sense not in ("lower", "higher", "two-sided"):
        raise ValueError(f"sense must be 'lower', 'higher' or 'two-sided', got {sense!r}")
    method = "bootstrap" if distribution == "radial" else "normal"
    if distribution not in ("normal", "radial"):
        raise ValueError(f"distribution must be 'normal' or 'radial', got {distribution!r}")
    mean_ci, std_ci = confidence_intervals(x, confidence, method, n_resamples=n_resamples, seed=seed)
    if sense == "lower":
        pass_mean = mean_ci[0] <= contract_mean
    elif sense == "higher":
        pass_mean = mean_ci[1] >= contract_mean
    else:
        pass_mean = mean_ci[0] <= contract_mean <= mean_ci[1]
    pass_std = True if contract_std is None else bool(std_ci[0] <= contract_std)
    sufficient = x.size >= n_required
    shape = scale = float("nan")
    if distribution == "radial" and np.all(x > 0) and x.size >= 3 and np.ptp(x) > 0:
        shape, _, scale = (float(v) for v in stats.weibull_min.fit(x, floc=0.0))  # pyright: ignore[reportArgumentType]
    # Shapiro-Wilk's p-value is accurate up to 5000 values; D'Agostino-Pearson beyond
    normality_p = float("nan")
    if x.size >= 3 and np.ptp(x) > 0:
        normality_p = float((stats.shapiro(x) if x.size <= 5000 else stats.normaltest(x)).pvalue)
    return Level1Result(
        n=int(x.size),
        n_required=int(n_required),
        mean=float(x.mean()),
        std=float(x.std(ddof=1)),
        mean_ci=(float(mean_ci[0]), float(mean_ci[1])),
        std_ci=(float(std_ci[0]), float(std_ci[1])),
        contract_mean=float(contract_mean),
        contract_std=None if contract_std is None else float(contract_std),
        pass_mean=bool(pass_mean),
        pass_std=bool(pass_std),
        sufficient_sample=bool(sufficient),
        passed=bool(pass_mean and pass_std and sufficient),
        method="normal"
        if method != "bootstrap"
        else "bootstrap-bca"
        if x.size <= BCA_MAX_VALUES
        else "bootstrap-percentile",
        p95=float(np.percentile(x, 95)),
        weibull_shape=shape,
        weibull_scale=scale,
        normality_p=normality_p,
    )
