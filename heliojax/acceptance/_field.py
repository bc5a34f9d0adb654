"""The heliostat field as the acceptance analysis sees it, and the parameters it knows."""

from __future__ import annotations

import dataclasses
import typing
from typing import Literal

import equinox as eqx
import numpy as np
from jaxtyping import Bool, Float


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
        n = len(self.ids)
        if len(set(self.ids)) != n:
            raise ValueError("heliostat IDs must be unique")
        if np.shape(self.positions) != (n, 3):
            raise ValueError(f"positions must have shape ({n}, 3), got {np.shape(self.positions)}")
        for k, v in self.values.items():
            if k not in PARAMETERS:
                raise ValueError(f"unknown parameter {k!r}; known: {sorted(PARAMETERS)}")
            if np.shape(v) != (n,):
                raise ValueError(f"values[{k!r}] must have shape ({n},), got {np.shape(v)}")

    @property
    def n(self) -> int:
        return len(self.ids)

    def measured(self, name: str) -> Bool[np.ndarray, " n"]:
        """Mask of the heliostats where parameter ``name`` was measured."""
        v = self.values.get(name)
        return np.zeros(self.n, dtype=bool) if v is None else np.isfinite(v)


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
    """
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
