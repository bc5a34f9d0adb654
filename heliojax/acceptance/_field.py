"""The heliostat field as the acceptance analysis sees it, and the parameters it knows."""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Literal

import equinox as eqx
import numpy as np
from jaxtyping import Bool, Float

from .._geometry import MAX_FIELD_EXTENT_M
from .._limits import MAX_SYNTHETIC_HELIOSTATS, count_problem
from ..paint._common import MAX_HELIOSTAT_HEIGHT_M


@dataclasses.dataclass(frozen=True)
class ParameterInfo:
    """Static description of an acceptance parameter.

    Attributes:
        unit: unit of the values.
        sense: which direction is better: ``"lower"`` or ``"higher"``.
        support: ``"positive"`` (KDE on log-values) or ``"unit"`` (KDE on logits).
        distribution: ``"radial"`` (2-D radial error; Rayleigh/Weibull-like) or
            ``"normal"``.
        maximum: the largest value that can be a measurement of a heliostat (in
            ``unit``); a larger one is a data error.
    """

    unit: str
    sense: Literal["lower", "higher", "two-sided"]
    support: Literal["positive", "unit", "real"]
    distribution: Literal["radial", "normal"]
    maximum: float


PARAMETERS: dict[str, ParameterInfo] = {
    "tracking_mrad": ParameterInfo("mrad", "lower", "positive", "radial", 1000.0),  # a beam 57 deg off
    "slope_mrad": ParameterInfo("mrad", "lower", "positive", "radial", 1000.0),
    "reflectance": ParameterInfo("1", "higher", "unit", "normal", 1.0),
    "aperture_m2": ParameterInfo("m^2", "higher", "positive", "normal", 10_000.0),  # the largest are ~200 m^2
}
"""The parameters of the guideline, keyed by their CSV column name.

``tracking_mrad``: radial RMS beam pointing error of the heliostat (angle between
the actual and the ideal reflected ray), as heliojax's calibration reports it
(``test_rms_mrad``). ``slope_mrad``: radial RMS slope deviation of the mirror
surface normal (SolarPACES ``SD``). ``reflectance``: solar-weighted specular
reflectance (fraction). ``aperture_m2``: net reflective aperture area.
"""


def _outside_support(support: str, a: np.ndarray) -> np.ndarray:
    """Where the values ``a`` lie outside the support ``support`` (NaN: False for
    ``"positive"``, True for ``"unit"``; callers leave NaN out first)."""
    with np.errstate(invalid="ignore"):
        if support == "positive":
            return np.asarray(a <= 0)
        if support == "unit":
            return np.asarray(~((a > 0) & (a < 1)))
        return np.zeros(np.shape(a), bool)


def value_problem(name: str, x: float) -> str | None:
    """Why ``x`` cannot be a measured value of parameter ``name`` (NaN: not measured, no
    problem), or None: not finite, outside the parameter's support or above its
    :attr:`ParameterInfo.maximum`. The one rule of the field CSV's reader and of
    :class:`FieldData`."""
    if math.isnan(x):
        return None
    info = PARAMETERS[name]
    if not math.isfinite(x):
        return f"{x} is not finite (NaN marks a value not measured)"
    if _outside_support(info.support, np.asarray(x)):
        return f"{x} outside the {info.support} range"
    if x > info.maximum:
        return f"{x} above {info.maximum:g} {info.unit}: no measurement"
    return None


@typing.final
class FieldData(eqx.Module):
    """Every heliostat of the field, with the parameters measured so far.

    Attributes:
        ids: heliostat IDs, length ``n``.
        positions: ``(n, 3)`` ENU m (east, north, up; up may be 0).
        values: parameter name -> ``(n,)`` values, NaN where not measured.
    """

    ids: tuple[str, ...] = eqx.field(static=True)
    positions: Float[np.ndarray, "n 3"]
    values: dict[str, Float[np.ndarray, " n"]]

    def __check_init__(self):
        # the field CSV reader's rules (it names the line first): a string of ids was
        # read as one id per letter, an infinite value as "not measured", a NaN position
        # failed in SciPy's KD-tree and a negative tracking error in the KDE's logarithm
        if isinstance(self.ids, str) or not all(isinstance(h, str) and h.strip() for h in self.ids):
            raise TypeError(f"ids: expected a tuple of heliostat ids (non-blank strings), got {self.ids!r}"[:200])
        n = len(self.ids)
        if len(set(self.ids)) != n:
            raise ValueError("heliostat IDs must be unique")
        if np.shape(self.positions) != (n, 3):
            raise ValueError(f"positions must have shape ({n}, 3), got {np.shape(self.positions)}")
        if not isinstance(self.values, dict):
            raise TypeError(f"values: expected a dict parameter name -> (n,) values, got {type(self.values).__name__}")
        pos = _numbers("positions", self.positions)
        far = ~(np.abs(pos) <= MAX_FIELD_EXTENT_M).all(axis=1) | ~(np.abs(pos[:, 2]) <= MAX_HELIOSTAT_HEIGHT_M)
        if far.any():
            i = int(np.argmax(far))
            raise ValueError(
                f"positions: heliostat {self.ids[i]!r} at {pos[i].tolist()} m: not finite or farther than "
                f"{MAX_FIELD_EXTENT_M:g} m from the tower (or {MAX_HELIOSTAT_HEIGHT_M:g} m above or below it)"
            )
        for k, v in self.values.items():
            if k not in PARAMETERS:
                raise ValueError(f"unknown parameter {k!r}; known: {sorted(PARAMETERS)}")
            if np.shape(v) != (n,):
                raise ValueError(f"values[{k!r}] must have shape ({n},), got {np.shape(v)}")
            a, info = _numbers(f"values[{k!r}]", v), PARAMETERS[k]
            with np.errstate(invalid="ignore"):  # value_problem for every heliostat at once (NaN: not measured)
                bad = ~np.isnan(a) & (~np.isfinite(a) | _outside_support(info.support, a) | (a > info.maximum))
            if bad.any():
                i = int(np.argmax(bad))
                raise ValueError(f"values[{k!r}]: heliostat {self.ids[i]!r}: {value_problem(k, float(a[i]))}")

    @property
    def n(self) -> int:
        return len(self.ids)

    def measured(self, name: str) -> Bool[np.ndarray, " n"]:
        """Mask of the heliostats where parameter ``name`` was measured."""
        v = self.values.get(name)
        return np.zeros(self.n, dtype=bool) if v is None else np.isfinite(v)


def field_indices(name: str, indices: object, n: int) -> np.ndarray:
    """``indices`` (heliostats of a field of ``n``) as a 1-D int array, or a ValueError
    naming ``name``: not whole numbers (2.5 was cut to 2), negative (-1 was read as the
    last heliostat of the field), ``n`` or more (an IndexError inside NumPy) or one
    given twice."""
    a = np.asarray(indices)
    if a.size == 0:
        return np.zeros(0, dtype=int)
    if a.ndim != 1 or a.dtype.kind not in "iuf" or (a.dtype.kind == "f" and not np.all(a == np.round(a))):
        raise ValueError(f"{name}: expected a 1-D array of heliostat indices (whole numbers), got {a!r}"[:200])
    a = a.astype(np.int64)
    bad = a[(a < 0) | (a >= n)]
    if bad.size:
        raise ValueError(f"{name}: heliostat index {int(bad[0])} outside the field's [0, {n - 1}]")
    unique, counts = np.unique(a, return_counts=True)
    if (counts > 1).any():
        raise ValueError(f"{name}: heliostat index {int(unique[counts > 1][0])} given twice")
    return a


def _numbers(name: str, array: object) -> np.ndarray:
    """``array`` as float64, or a TypeError naming ``name`` (strings, objects, booleans)."""
    a = np.asarray(array)
    if a.dtype.kind not in "iuf":
        raise TypeError(f"{name}: expected numbers, got an array of dtype {a.dtype}")
    return a.astype(np.float64)


def synthetic_field(
    n: int = 1001,
    *,
    seed: int = 0,
    cluster_size: int = 120,
    cluster_centre_m: tuple[float, float] = (-45.0, 95.0),
    tracking: tuple[float, float] = (1.7, 0.3),
    cluster_tracking: tuple[float, float] = (2.8, 0.4),
    slope: tuple[float, float] = (1.5, 0.3),
    reflectance: tuple[float, float] = (0.94, 0.0015),
    aperture: tuple[float, float] = (8.0, 0.0064),
) -> tuple[FieldData, Bool[np.ndarray, " n"]]:
    """A Jülich-like synthetic field (the guideline's subfield example) with a block
    of recently refurbished heliostats whose tracking is worse.

    Layout: radially staggered rows north of the tower (origin), first row at
    30 m, row pitch 5.5 m, 4.6 m between heliostats along a row, +-55 deg about
    north, filled until ``n`` heliostats. The ``cluster_size`` heliostats nearest
    to ``cluster_centre_m`` form the refurbished block.

    Per-heliostat values ("truth", all measured): tracking and slope errors are
    gamma-distributed (positive, right-skewed) with the given (mean, std) in
    mrad; reflectance and aperture are normal with the given (mean, std).

    Returns:
        ``(field, in_cluster)``: the field and the ``(n,)`` mask of the block.

    Raises:
        ValueError: ``n`` not a whole number >= 1 or ``cluster_size`` not one in
            ``[0, n]`` (0 heliostats had failed in a NumPy concatenation).
    """
    for name, value, least, most in (("n", n, 1, MAX_SYNTHETIC_HELIOSTATS), ("cluster_size", cluster_size, 0, n)):
        problem = count_problem(value, most, minimum=least)
        if problem is not None:
            raise ValueError(f"synthetic_field: {name} {problem}")
    rng = np.random.default_rng(seed)
    pts = []
    r, row = 30.0, 0
    while sum(len(p) for p in pts) < n:
        half = np.deg2rad(55.0)
        m = int(2 * half * r / 4.6)
        ang = -half + (np.arange(m) + 0.5 * (row % 2) + 0.25) * (2 * half / m)
        pts.append(np.column_stack([r * np.sin(ang), r * np.cos(ang)]))
        r += 5.5
        row += 1
    xy = np.concatenate(pts)[:n]
    enu = np.column_stack([xy, np.zeros(n)])
    d = np.hypot(xy[:, 0] - cluster_centre_m[0], xy[:, 1] - cluster_centre_m[1])
    in_cluster = np.zeros(n, dtype=bool)
    in_cluster[np.argsort(d)[:cluster_size]] = True

    def gamma(mean, std, size):
        k = (mean / std) ** 2
        return rng.gamma(k, mean / k, size)

    track = gamma(*tracking, n)
    track[in_cluster] = gamma(*cluster_tracking, int(in_cluster.sum()))
    values = {
        "tracking_mrad": track,
        "slope_mrad": gamma(*slope, n),
        "reflectance": rng.normal(reflectance[0], reflectance[1], n),
        "aperture_m2": rng.normal(aperture[0], aperture[1], n),
    }
    ids = tuple(f"S{i:04d}" for i in range(n))
    return FieldData(ids=ids, positions=enu, values=values), in_cluster
