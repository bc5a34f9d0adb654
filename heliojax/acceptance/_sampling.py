"""Sample sizes (Röger et al., SolarPACES heliostat field performance testing
guideline, Eqs. 3-8) and random selection of the heliostats to measure.

Notation of the guideline: estimated mean ``mu_e`` and standard deviation
``sigma_e`` of a parameter over the field, coefficient of variation
``V = sigma_e / mu_e``, relative error margin ``e* = e / mu_e`` (half-width of the
confidence interval of the mean relative to the mean), standard normal deviate
``z`` (1.96 for 95 %), field size ``N``:

* Eq. 3 / 4 (sampling with replacement, or an infinite field):
  ``n0 = z^2 sigma^2 / e^2 = z^2 V^2 / e*^2``;
* Eq. 6 / 7 (finite field, sampling without replacement):
  ``n = n0 / ((1 - 1/N) + n0 / N)``;
* Eq. 8 (Slovin-type simplification for ``N > 100``): ``n = n0 / (1 + n0 / N)``.

``n`` is rounded **up** to the next integer (a small tolerance absorbs float
round-off, so an exact integer is not bumped up by one).

Published numbers and the formula
---------------------------------
Every sample size printed in the paper is reproduced by these functions
(``tests/test_acceptance_sampling.py``) except three, which the formula
(rounded up, as the paper says) does not give:

* N = 1001, reflectance V = 0.0015, e* = 0.1 %: Eq. 7 gives 8.58 -> **9**; the
  paper prints 10.
* N = 14500, reflectance mu = 94 %, sigma = 0.8 %, e* = 0.1 %: Eq. 7 gives
  273.03 -> **274**; the paper prints 273 (the upper end of "18 to 273").
* N = 10000, V = 0.20, e* = 5 %: Eq. 7 gives 61.10 -> **62** (Eq. 8: 61.09 ->
  62); the paper's table prints 61 for both.

The exact deviate ``z = 1.959964`` instead of the rounded 1.96 changes none of
the published values (the largest effect is 273.030 -> 273.020); pass
``z=1.96`` to use the paper's rounded value explicitly.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from jaxtyping import Float, Int
from scipy.stats import norm

from .._limits import count_problem
from ._field import field_indices

Formula = Literal["eq4", "eq7", "eq8"]

_ROUND_TOL = 1e-9


def z_value(confidence: float = 0.95) -> float:
    """Two-sided standard normal deviate ``z = Phi^-1((1 + confidence) / 2)``.

    Args:
        confidence: confidence level in (0, 1); 0.95 gives 1.959964.
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    return float(norm.ppf(0.5 * (1.0 + confidence)))


def _ceil(x: float) -> int:
    return int(math.ceil(x - _ROUND_TOL * max(1.0, abs(x))))


def _finite_population(n0: float, population: int | None, formula: Formula) -> float:
    if formula == "eq4":
        return n0
    if formula not in ("eq7", "eq8"):
        raise ValueError(f"formula must be 'eq4', 'eq7' or 'eq8', got {formula!r}")
    if population is None:
        raise ValueError(f"formula {formula!r} needs the field size `population`")
    problem = count_problem(population, 10**9)  # 2.5 heliostats had been taken
    if problem is not None:
        raise ValueError(f"population {problem}")
    n_pop = float(population)
    if formula == "eq7":
        return n0 / ((1.0 - 1.0 / n_pop) + n0 / n_pop)
    return n0 / (1.0 + n0 / n_pop)


def sample_size_absolute(
    std: float,
    error: float,
    population: int | None = None,
    confidence: float = 0.95,
    formula: Formula = "eq7",
    *,
    z: float | None = None,
) -> int:
    """Sample size from the absolute form (Eqs. 3 and 6 of the guideline).

    Args:
        std: estimated standard deviation ``sigma_e`` of the parameter over the
            field (any unit).
        error: absolute error margin ``e`` (same unit): half-width of the
            confidence interval of the mean.
        population: field size ``N`` (required for ``"eq7"`` / ``"eq8"``).
        confidence: two-sided confidence level (0.95 -> z = 1.96).
        formula: ``"eq4"`` (Eq. 3, with replacement), ``"eq7"`` (Eq. 6, finite
            field) or ``"eq8"`` (Slovin form).
        z: override of the standard normal deviate (e.g. the paper's 1.96).

    Returns:
        The number of heliostats to measure, rounded up (at least 1, at most N).
    """
    if not (std >= 0.0 and math.isfinite(std)):
        raise ValueError(f"std must be finite and >= 0, got {std}")
    if not (error > 0.0 and math.isfinite(error)):
        raise ValueError(f"error must be finite and > 0, got {error}")
    zz = z_value(confidence) if z is None else float(z)
    n0 = (zz * std / error) ** 2  # one ratio: std**2 and error**2 alone may underflow
    n = _ceil(_finite_population(n0, population, formula))
    n = max(n, 1)
    if population is not None:
        n = min(n, int(population))
    return n


def sample_size(
    mean: float,
    std: float,
    rel_error: float,
    population: int | None = None,
    confidence: float = 0.95,
    formula: Formula = "eq7",
    *,
    z: float | None = None,
) -> int:
    """Number of heliostats to measure for one parameter (relative form, Eqs. 4, 7, 8).

    ``V = std / mean`` is used unrounded.

    Args:
        mean: estimated field mean ``mu_e`` (any unit, non-zero).
        std: estimated field standard deviation ``sigma_e`` (same unit).
        rel_error: relative error margin ``e*`` (0.05 = 5 % of the mean).
        population: field size ``N`` (required for ``"eq7"`` / ``"eq8"``).
        confidence: two-sided confidence level (0.95 -> z = 1.959964).
        formula: ``"eq4"``, ``"eq7"`` or ``"eq8"``.
        z: override of the standard normal deviate (the paper uses 1.96; no
            published value depends on the difference).

    Returns:
        ``n`` rounded up (at least 1, at most ``population``).

    Example:
        >>> sample_size(2.0, 0.2, 0.04, population=1001)  # tracking, Jülich example
        24
    """
    if not (mean != 0.0 and math.isfinite(mean)):
        raise ValueError(f"mean must be finite and non-zero, got {mean}")
    if not (rel_error > 0.0 and math.isfinite(rel_error)):
        raise ValueError(f"rel_error must be finite and > 0, got {rel_error}")
    return sample_size_absolute(abs(std / mean), rel_error, population, confidence, formula, z=z)


def select_sample(
    positions: Float[np.ndarray, "N _"],
    n: int,
    *,
    seed: int | np.random.Generator = 0,
    method: Literal["random", "stratified"] = "stratified",
    exclude: Int[np.ndarray, " m"] | None = None,
) -> Int[np.ndarray, " k"]:
    """Pick ``n`` heliostats to measure, at random.

    ``"random"`` is simple random sampling without replacement (the guideline's
    assumption behind Eqs. 4-8). ``"stratified"`` splits the field into ``n``
    compact spatial strata of (nearly) equal size (equal-count sectors by
    angle about the field centroid, each cut into equal-count cells by radius)
    and draws one heliostat at random per stratum: still a random sample with equal inclusion probability per
    heliostat, but it cannot miss a whole region of the field, which makes local
    anomalies (a refurbished block) much more likely to be hit.

    Args:
        positions: ``(N, 2)`` east, north in m (or ``(N, k)``; only the first two
            columns are used).
        n: sample size (``<= N`` minus excluded).
        seed: integer seed or a numpy ``Generator``.
        method: ``"random"`` or ``"stratified"``.
        exclude: indices that must not be drawn (already measured).

    Returns:
        ``(n,)`` sorted indices into ``positions``.

    Raises:
        ValueError: ``positions`` not ``(N, >= 2)`` or not finite (a NaN had surfaced
            as "cannot convert float NaN to integer"), ``n`` not an integer between 0
            and the heliostats available, an unknown ``method``, ``exclude`` of indices
            outside the field, not whole or given twice (an IndexError inside NumPy;
            -1 excluded the last heliostat).
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    xy = np.asarray(positions, dtype=float)
    if xy.ndim != 2 or xy.shape[1] < 2:
        raise ValueError(f"select_sample: positions has shape {xy.shape}; expected (N, 2) east, north in m")
    xy = xy[:, :2]
    if not np.isfinite(xy).all():
        bad = np.flatnonzero(~np.isfinite(xy).all(axis=1))
        raise ValueError(
            f"select_sample: positions of {bad.size} heliostat(s) are not finite (first: row {int(bad[0])}); "
            "expected east, north in m for every heliostat"
        )
    if isinstance(n, bool) or not isinstance(n, int | np.integer):
        raise ValueError(f"select_sample: n must be an integer, got {n!r}")
    avail = np.ones(len(xy), dtype=bool)
    if exclude is not None:
        avail[field_indices("exclude", exclude, len(xy))] = False
    idx = np.flatnonzero(avail)
    if not 0 <= n <= idx.size:
        raise ValueError(f"cannot draw {n} heliostats from {idx.size} available")
    if n == 0:
        return np.zeros(0, dtype=int)
    if method == "random":
        return np.sort(rng.choice(idx, size=n, replace=False))
    if method != "stratified":
        raise ValueError(f"method must be 'random' or 'stratified', got {method!r}")
    strata = _equal_strata(xy[idx], n)
    # one random member per stratum, vectorised: random key, take the argmin per stratum
    key = rng.random(idx.size)
    order = np.lexsort((key, strata))
    first = np.r_[0, np.flatnonzero(np.diff(strata[order])) + 1]
    return np.sort(idx[order[first]])


def _equal_strata(xy: np.ndarray, k: int) -> np.ndarray:
    """Label each point with one of ``k`` compact strata of equal size (+-1).

    Points are sorted by polar angle about the centroid into ``r`` angular
    sectors, then each sector by radius into equal-count cells; ``r`` is chosen
    so that cells are roughly square for a wedge-shaped heliostat field.
    """
    m = len(xy)
    c = xy.mean(axis=0)
    d = xy - c
    ang = np.arctan2(d[:, 0], d[:, 1])
    rad = np.hypot(d[:, 0], d[:, 1])
    # sectors ~ sqrt(k) scaled by the aspect ratio of the point cloud
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(d.T)), 1e-12))
    n_sec = int(np.clip(round(math.sqrt(k * spread[1] / spread[0])), 1, k))
    sector = np.empty(m, dtype=int)
    sector[np.argsort(ang, kind="stable")] = (np.arange(m) * n_sec) // m
    # distribute the k strata over sectors in proportion to their counts
    counts = np.bincount(sector, minlength=n_sec)
    per = np.floor(counts / m * k).astype(int)
    rest = k - per.sum()
    per[np.argsort(-(counts / m * k - per), kind="stable")[:rest]] += 1
    label = np.empty(m, dtype=int)
    base = np.r_[0, np.cumsum(per)[:-1]]
    for s in range(n_sec):  # loop over sectors (~sqrt(k)), not heliostats
        members = np.flatnonzero(sector == s)
        within = members[np.argsort(rad[members], kind="stable")]
        label[within] = base[s] + (np.arange(members.size) * per[s]) // max(members.size, 1)
    return label
