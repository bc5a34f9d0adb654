"""Fleets: PAINT records as typed, padded pytrees.

A :class:`Fleet` holds ``H`` heliostats with up to ``M`` records each, as
batched arrays with a validity ``mask`` so that heliostats with different
record counts share one compiled program (vmap over the heliostat axis; mask
the record axis). All positions are ENU metres about the tower file's
``power_plant_properties.coordinates`` (see :mod:`heliojax._geometry`).

Assembly (:func:`records_to_fleet`, shared by the directory loader, the CSV
loader and the simulator)
------------------------------------------------------------------------------
* Heliostats are sorted by id. A heliostat with properties but no valid record
  is kept (all-False mask) and flagged; records of a heliostat without
  properties are skipped and reported (one entry per heliostat).
* Records of a heliostat are sorted chronologically (ties: record id). Records
  without a time are placed by record id among the timed ones (PAINT record ids
  are sequential in time: the 1,706 timestamped ids of the shared download are
  strictly chronological); they keep ``unix_time = NaN`` and are flagged.
* ``approach``: for each axis the sign of the last count change before the
  record, over the heliostat's records in that order (0 for the first record and
  until the axis first moves). It is a proxy: the heliostat also moves between
  calibration records.
* Centroid: ``centroid="utis"`` (default) uses UTIS and falls back to HeliOS
  where UTIS is absent or null (counted in ``report.centroid_fallbacks``);
  ``"helios"`` uses HeliOS only (records without it are skipped and reported).
* Sun direction from the recorded azimuth/elevation; the weather
  (``temperature`` deg C, ``wind_speed`` m/s, ``wind_direction`` rad clockwise
  from north, the direction the wind comes from) is NaN where unknown.
* Padded record slots (``mask`` False, ``record_id`` -1) are copies of the
  heliostat's first valid record, so every value there is as finite as real data
  (motor counts, sun, focal spot are always finite; time and weather are NaN
  exactly where the copied record's are). A heliostat without any valid record
  gets one synthetic slot: mid-range counts, sun at azimuth 0 / elevation 45 deg,
  focal spot at the centre of target 0. Padding heliostats (:func:`pad_fleet`)
  are copies of heliostat 0 with an all-False mask and id ``""``.
* Geodesy (WGS84 -> ENU) is always computed in float64 (inside
  ``jax.enable_x64``); the arrays of the fleet then take JAX's default float
  dtype (float64 when ``jax_enable_x64`` is on, as it must be for calibration).

Suspicious-but-loaded inputs (``report.flags``)
-----------------------------------------------
*Actuator outliers.* For each number that sets the counts-to-angle law or the
axis offsets (per axis: ``increment``, ``initial_stroke_length``, ``offset``,
``pivot_radius``, ``initial_angle``; the nine joint/concentrator translation
components), a heliostat is flagged when::

    |value - median| > K * max(1.4826 * MAD, FLOOR * scale)        K = 5, FLOOR = 0.01

over the fleet being loaded (at least 3 heliostats). ``1.4826 MAD`` is the
robust estimate of the standard deviation of normal scatter; ``K = 5`` makes a
false flag of normal scatter a 6e-7 event per value (about 1 in 10^4 fleets of
30 heliostats x 28 values), while real data errors (a wrong unit, a value from
another actuator or heliostat, a swapped field) sit tens of sigma out. The
floor keeps design constants that are identical across the fleet
(``offset``, ``pivot_radius``, ``increment``, the translations: MAD = 0) from
flagging at the last digit: a deviation below 1 % of the quantity's natural
scale is within fabrication and survey tolerance. The scale is ``|median|`` for
lengths and increments, the median range of motion of the axis (the actuator
law's angle span over ``[min_increment, max_increment]``) for ``initial_angle``,
and the median mirror width for the translations. *Triangle check.* Flagged
too: an actuator whose stroke over ``[min_increment, max_increment]`` leaves
``[|offset - pivot_radius|, offset + pivot_radius]`` (the law of cosines has no
solution there and the angle saturates), and a ``clockwise_axis_movement``
that differs from the fleet's majority.
"""

from __future__ import annotations

import collections
import dataclasses
import importlib.resources
import math
import os
import re
import typing
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._errors import DataError
from ._geometry import TargetPlane, sun_direction, wgs84_to_enu
from ._kinematics import HeliostatGeometry, LinearActuators, RecordContext
from ._paint import (
    CALIBRATION_SUFFIX,
    CORNERS,
    PROPERTIES_SUFFIX,
    TIMESTAMPS_FILE,
    TOWER_FILE_SUFFIX,
    WEATHER_CSV_FILE,
    CalibrationRecord,
    HeliostatProperties,
    TowerFile,
    check_record_context,
    heliostat_properties_path,
    read_calibration_record,
    read_heliostat_properties,
    read_timestamps,
    read_tower,
    read_weather_csv,
    validate_properties,
    validate_record,
)
from ._sun import datetime_to_unix

__all__ = [
    "OUTLIER_FLOOR",
    "OUTLIER_K",
    "Fleet",
    "HeliostatRecords",
    "LoadReport",
    "ReportEntry",
    "bucket_size",
    "default_data_dir",
    "fleet_subset",
    "load_paint_directory",
    "load_weather_csv_fleet",
    "pad_fleet",
    "records_to_fleet",
]

Centroid = Literal["utis", "helios"]
_CENTROIDS = ("utis", "helios")

OUTLIER_K = 5.0
"""Robust outlier threshold in (robust) standard deviations."""
OUTLIER_FLOOR = 0.01
"""Relative floor of the robust scale (fraction of the quantity's natural scale)."""
_MIN_FLEET_FOR_OUTLIERS = 3


# ======================================================================================
# Load report
# ======================================================================================


class ReportEntry(NamedTuple):
    """One skipped or flagged input: the file, the dotted field (or None) and why."""

    file: str
    field: str | None
    reason: str


@dataclasses.dataclass(frozen=True)
class LoadReport:
    """What a load saw, loaded, skipped and flagged (hashable: a static field of
    :class:`Fleet`).

    Attributes:
        source: the directory / CSV file / ``"<records>"``.
        files_seen: files read (tower, timestamps, CSV, properties, calibration).
        records_loaded: valid records in the fleet.
        records_skipped: records not in the fleet (each is accounted for in ``skipped``).
        heliostats_loaded: heliostats in the fleet (padding excluded).
        heliostats_skipped: heliostats not in the fleet.
        records_without_time: loaded records whose time is unknown (NaN).
        records_with_weather: loaded records with at least one known weather value.
        centroid: ``"utis"`` or ``"helios"``.
        centroid_fallbacks: loaded records that use HeliOS because UTIS is missing
            (``centroid="utis"``).
        skipped: ``(file, field, reason)`` of everything skipped.
        flags: ``(file, field, reason)`` of suspicious inputs that were loaded.
        notes: other remarks (missing optional files, checks not run).
    """

    source: str
    files_seen: int = 0
    records_loaded: int = 0
    records_skipped: int = 0
    heliostats_loaded: int = 0
    heliostats_skipped: int = 0
    records_without_time: int = 0
    records_with_weather: int = 0
    centroid: str = "utis"
    centroid_fallbacks: int = 0
    skipped: tuple[ReportEntry, ...] = ()
    flags: tuple[ReportEntry, ...] = ()
    notes: tuple[str, ...] = ()

    def format(self) -> str:
        """A human-readable table of counts, skipped inputs and flags."""
        root = self.source

        def rel(f: str) -> str:
            if Path(f) == Path(root):
                return Path(f).name or f
            try:
                return str(Path(f).relative_to(root))
            except ValueError:
                return f

        lines = [
            f"Load report: {self.source}",
            f"  files seen            {self.files_seen:6d}",
            f"  heliostats loaded     {self.heliostats_loaded:6d}   skipped {self.heliostats_skipped}",
            f"  records loaded        {self.records_loaded:6d}   skipped {self.records_skipped}",
            f"  records without time  {self.records_without_time:6d}   (kept, time NaN)",
            f"  records with weather  {self.records_with_weather:6d}",
            f"  centroid              {self.centroid:>6s}   HeliOS fallbacks {self.centroid_fallbacks}",
        ]
        for title, entries in (("Skipped", self.skipped), ("Flags", self.flags)):
            lines.append(f"{title} ({len(entries)}):")
            if not entries:
                lines.append("  (none)")
                continue
            files = [rel(e.file) for e in entries]
            fields = [e.field or "-" for e in entries]
            wf = min(max(len(s) for s in files + ["FILE"]), 60)
            wd = min(max(len(s) for s in fields + ["FIELD"]), 48)
            lines.append(f"  {'FILE':<{wf}}  {'FIELD':<{wd}}  REASON")
            for f, d, e in zip(files, fields, entries):
                lines.append(f"  {f:<{wf}}  {d:<{wd}}  {e.reason}")
        if self.notes:
            lines.append("Notes:")
            lines.extend(f"  {n}" for n in self.notes)
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.format()


class _Log:
    """Mutable collector behind a :class:`LoadReport`."""

    def __init__(self, source: str, strict: bool, centroid: str):
        self.source = source
        self.strict = strict
        self.centroid = centroid
        self.files_seen = 0
        self.records_skipped = 0
        self.heliostats_skipped = 0
        self.skipped: list[ReportEntry] = []
        self.flags: list[ReportEntry] = []
        self.notes: list[str] = []

    def skip(self, err: DataError, records: int = 0, heliostats: int = 0) -> None:
        if self.strict:
            raise err
        self.skipped.append(ReportEntry(str(err.file), err.field, err.reason))
        self.records_skipped += records
        self.heliostats_skipped += heliostats

    def skip_record(self, err: DataError) -> None:
        self.skip(err, records=1)

    def skip_entry(self, err: DataError) -> None:
        self.skip(err)

    def flag(self, file: str, field: str | None, reason: str) -> None:
        self.flags.append(ReportEntry(str(file), field, reason))

    def report(self, **counts) -> LoadReport:
        return LoadReport(
            source=self.source,
            files_seen=self.files_seen,
            records_skipped=self.records_skipped,
            heliostats_skipped=self.heliostats_skipped,
            centroid=self.centroid,
            skipped=tuple(self.skipped),
            flags=tuple(self.flags),
            notes=tuple(self.notes),
            **counts,
        )


# ======================================================================================
# Fleet
# ======================================================================================


@typing.final
class HeliostatRecords(eqx.Module):
    """One heliostat of a :class:`Fleet` (:meth:`Fleet.heliostat`): the fleet's
    per-heliostat arrays without the leading axis (``M`` records)."""

    geometry: HeliostatGeometry
    counts: Float[Array, "M 2"]
    context: RecordContext
    focal_spot: Float[Array, "M 3"]
    target_index: Int[Array, " M"]
    record_id: Int[Array, " M"]
    mask: Bool[Array, " M"]
    id: str = eqx.field(static=True)


@typing.final
class Fleet(eqx.Module):
    """Calibration records of ``H`` heliostats, padded to ``M`` records each.

    Attributes:
        geometry: batched :class:`HeliostatGeometry` (leading axis ``H``; ENU m, rad).
        counts: ``(H, M, 2)`` motor counts (axis 1, axis 2), float.
        context: batched :class:`RecordContext` ``(H, M, ...)``: ``sun`` unit ENU
            vectors from the recorded azimuth/elevation, ``unix_time`` s (NaN unknown),
            ``temperature`` deg C, ``wind_speed`` m/s, ``wind_direction`` rad (NaN
            unknown), ``approach`` ``(H, M, 2)`` in {-1, 0, +1}.
        focal_spot: ``(H, M, 3)`` ENU m, the selected centroid.
        target_index: ``(H, M)`` index into ``targets`` / ``target_names``.
        record_id: ``(H, M)`` PAINT record id, -1 for padding.
        mask: ``(H, M)`` True for valid records.
        targets: batched :class:`TargetPlane` ``(T,)``, the tower file's planar targets.
        origin_lla: ``(3,)`` WGS84 ``[lat_deg, lon_deg, alt_m]`` of the ENU origin.
        ids: heliostat ids (``""`` for padding heliostats); static.
        target_names: names of ``targets``; static.
        report: the :class:`LoadReport`; static.
    """

    geometry: HeliostatGeometry
    counts: Float[Array, "H M 2"]
    context: RecordContext
    focal_spot: Float[Array, "H M 3"]
    target_index: Int[Array, "H M"]
    record_id: Int[Array, "H M"]
    mask: Bool[Array, "H M"]
    targets: TargetPlane
    origin_lla: Float[Array, "3"]
    ids: tuple[str, ...] = eqx.field(static=True)
    target_names: tuple[str, ...] = eqx.field(static=True)
    report: LoadReport = eqx.field(static=True)

    def __check_init__(self):
        h, m = jnp.shape(self.mask)
        checks = {
            "counts": (jnp.shape(self.counts), (h, m, 2)),
            "focal_spot": (jnp.shape(self.focal_spot), (h, m, 3)),
            "target_index": (jnp.shape(self.target_index), (h, m)),
            "record_id": (jnp.shape(self.record_id), (h, m)),
            "context.sun": (jnp.shape(self.context.sun), (h, m, 3)),
            "context.approach": (jnp.shape(self.context.approach), (h, m, 2)),
            "geometry.position": (jnp.shape(self.geometry.position), (h, 3)),
        }
        for name, (got, want) in checks.items():
            if tuple(got) != want:
                raise ValueError(f"Fleet.{name} has shape {got}, expected {want}")
        if len(self.ids) != h:
            raise ValueError(f"Fleet.ids has {len(self.ids)} entries for {h} heliostats")
        if len(self.target_names) != jnp.shape(self.targets.centre)[0]:
            raise ValueError("Fleet.target_names does not match targets")

    @property
    def n_heliostats(self) -> int:
        """``H`` (padding heliostats included)."""
        return int(jnp.shape(self.mask)[0])

    @property
    def n_records(self) -> int:
        """``M``, the padded record axis."""
        return int(jnp.shape(self.mask)[1])

    def index(self, heliostat_id: str) -> int:
        """Position of ``heliostat_id`` on the heliostat axis (ValueError if absent)."""
        if not heliostat_id or heliostat_id not in self.ids:
            raise ValueError(f"heliostat {heliostat_id!r} is not in the fleet")
        return self.ids.index(heliostat_id)

    def heliostat(self, i: int | str) -> HeliostatRecords:
        """The arrays of heliostat ``i`` (position, or id) without the leading axis."""
        if isinstance(i, str):
            i = self.index(i)
        i = int(i)
        if not -self.n_heliostats <= i < self.n_heliostats:
            raise IndexError(f"heliostat index {i} out of range for {self.n_heliostats}")
        xp = _backend(self)
        take = lambda x: _to_jax(xp.asarray(x)[i])  # noqa: E731
        return HeliostatRecords(
            geometry=jax.tree.map(take, self.geometry),
            counts=self.counts[i],
            context=jax.tree.map(take, self.context),
            focal_spot=self.focal_spot[i],
            target_index=self.target_index[i],
            record_id=self.record_id[i],
            mask=self.mask[i],
            id=self.ids[i],
        )


_PER_HELIOSTAT = ("geometry", "counts", "context", "focal_spot", "target_index", "record_id", "mask")


def _replace(fleet: Fleet, **changes) -> Fleet:
    """A new Fleet with some fields changed (runs the shape checks again)."""
    kw = {f.name: getattr(fleet, f.name) for f in dataclasses.fields(fleet)}
    kw.update(changes)
    return Fleet(**kw)


# ======================================================================================
# Shapes: buckets, padding, subsets
# ======================================================================================


def bucket_size(n: int) -> int:
    """Smallest shape bucket ``>= n``.

    Buckets are 8, 12, 16, 24, 32, 48, 64, 96, ... (``2^k`` and ``1.5 * 2^k`` for
    ``k >= 3``): a fleet whose size changes recompiles at most twice per doubling,
    and padding wastes at most a third of the slots (``n = 2^k + 1`` ->
    ``1.5 * 2^k``; ``n = 1.5 * 2^k + 1`` -> ``2^(k+1)``) beyond the minimum of 8.
    """
    n = int(n)
    if n < 0:
        raise ValueError(f"bucket_size of a negative size {n}")
    b = 8
    while True:
        if n <= b:
            return b
        if n <= b + b // 2:
            return b + b // 2
        b *= 2


def _backend(tree) -> typing.Any:
    """numpy for concrete arrays (no per-shape compilation), jax.numpy under tracing."""
    leaves = jax.tree.leaves(tree)
    return jnp if any(isinstance(x, jax.core.Tracer) for x in leaves) else np


def _to_jax(tree):
    """numpy leaves -> device arrays without a compilation (tracers pass through)."""
    return jax.tree.map(lambda x: x if isinstance(x, jax.core.Tracer) else jax.device_put(x), tree)


def pad_fleet(fleet: Fleet, n_heliostats: int | None = None, n_records: int | None = None) -> Fleet:
    """Pad a fleet to ``(n_heliostats, n_records)`` (default: :func:`bucket_size`
    of the current sizes).

    Padded record slots copy the heliostat's first valid record (slot 0 when none),
    with ``mask`` False and ``record_id`` -1; padding heliostats copy heliostat 0
    with an all-False mask, ``record_id`` -1 and id ``""``. Values in the valid
    region are unchanged. Shapes change, so call it outside ``jit`` (it works under
    tracing too, but then compiles per shape).

    Raises:
        ValueError: if a requested size is smaller than the fleet's.
    """
    h, m = fleet.n_heliostats, fleet.n_records
    nh = bucket_size(h) if n_heliostats is None else int(n_heliostats)
    nm = bucket_size(m) if n_records is None else int(n_records)
    if nh < h or nm < m:
        raise ValueError(f"cannot pad a fleet of shape ({h}, {m}) to ({nh}, {nm})")
    xp = _backend(fleet)
    rec = {k: getattr(fleet, k) for k in ("counts", "context", "focal_spot", "target_index")}
    rec = jax.tree.map(xp.asarray, rec)
    record_id = xp.asarray(fleet.record_id)
    mask = xp.asarray(fleet.mask)
    geometry = jax.tree.map(xp.asarray, fleet.geometry)
    if nm > m:
        src = xp.argmax(mask, axis=1)  # first valid record (0 if none)
        extra = nm - m

        def grow(x):
            fill = xp.take_along_axis(x, src.reshape((h, 1) + (1,) * (x.ndim - 2)), axis=1)
            return xp.concatenate([x, xp.repeat(fill, extra, axis=1)], axis=1)

        rec = jax.tree.map(grow, rec)
        record_id = xp.concatenate([record_id, xp.full((h, extra), -1, record_id.dtype)], 1)
        mask = xp.concatenate([mask, xp.zeros((h, extra), bool)], 1)
    ids = fleet.ids
    if nh > h:
        extra = nh - h

        def grow_h(x):
            return xp.concatenate([x, xp.repeat(x[:1], extra, axis=0)], axis=0)

        rec = jax.tree.map(grow_h, rec)
        geometry = jax.tree.map(grow_h, geometry)
        record_id = xp.concatenate([record_id, xp.full((extra, nm), -1, record_id.dtype)], 0)
        mask = xp.concatenate([mask, xp.zeros((extra, nm), bool)], 0)
        ids = ids + ("",) * extra
    return _replace(
        fleet,
        geometry=_to_jax(geometry),
        record_id=_to_jax(record_id),
        mask=_to_jax(mask),
        ids=ids,
        **_to_jax(rec),
    )


def fleet_subset(fleet: Fleet, indices: Sequence[int] | np.ndarray | int | str | Sequence[str]) -> Fleet:
    """The heliostats ``indices`` (positions or ids, in the given order) of a fleet;
    the record axis, targets and report are kept."""
    if isinstance(indices, (int, np.integer, str)):
        indices = [indices]
    idx = [fleet.index(i) if isinstance(i, str) else int(i) for i in indices]
    for i in idx:
        if not -fleet.n_heliostats <= i < fleet.n_heliostats:
            raise IndexError(f"heliostat index {i} out of range for {fleet.n_heliostats}")
    xp = _backend(fleet)
    sel = np.asarray(idx, dtype=np.int64)
    take = lambda x: _to_jax(xp.asarray(x)[sel])  # noqa: E731
    return _replace(
        fleet,
        **{k: jax.tree.map(take, getattr(fleet, k)) for k in _PER_HELIOSTAT},
        ids=tuple(fleet.ids[i] for i in idx),
    )


def default_data_dir() -> Path:
    """The embedded PAINT subset shipped with heliojax (``heliojax/data/paint``):
    5 heliostats of the Jülich tower (CDLA-Permissive-2.0, see its NOTICE)."""
    return Path(str(importlib.resources.files("heliojax") / "data" / "paint"))


# ======================================================================================
# Assembly
# ======================================================================================


def _check_centroid(centroid: str) -> None:
    if centroid not in _CENTROIDS:
        raise ValueError(f"centroid must be one of {_CENTROIDS}, got {centroid!r}")


def _common_dir(sources: Sequence[str]) -> str:
    """The one file (CSV rows ``path:line``) or the one directory the sources share."""
    files = {re.sub(r":[0-9]+$", "", s) for s in sources}
    if len(files) == 1:
        return files.pop()
    parents = {str(Path(f).parent) for f in files}
    if len(parents) == 1 and parents != {"."}:
        return parents.pop()
    return sources[0]


def _chronological(records: list[CalibrationRecord], times: list[float]) -> list[int]:
    """Indices of ``records`` in chronological order (ties: record id); records of
    unknown time are placed by record id among the timed ones."""
    known = sorted((t, records[k].record_id, k) for k, t in enumerate(times) if math.isfinite(t))
    unknown = sorted((records[k].record_id, k) for k, t in enumerate(times) if not math.isfinite(t))
    order: list[int] = []
    u = 0
    for _, rid, k in known:
        while u < len(unknown) and unknown[u][0] < rid:
            order.append(unknown[u][1])
            u += 1
        order.append(k)
    order.extend(k for _, k in unknown[u:])
    return order


def _approach(counts: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(H, M, 2)`` sign of the last count change before each record (valid
    records first along M, in chronological order)."""
    h, m, _ = counts.shape
    step = np.zeros_like(counts)
    if m > 1:
        both = (mask[:, 1:] & mask[:, :-1])[..., None]
        step[:, 1:] = np.where(both, np.sign(counts[:, 1:] - counts[:, :-1]), 0.0)
    pos = np.arange(m)[None, :, None]
    last = np.maximum.accumulate(np.where(step != 0, pos, 0), axis=1)
    return np.take_along_axis(step, last, axis=1) * mask[..., None]


def _actuator_law(inc, s0, a, b, ang0, sign, counts):
    def psi(s):
        return np.arccos(np.clip((a**2 + b**2 - s**2) / (2 * a * b), -1.0, 1.0))

    return ang0 + sign * (psi(counts / inc + s0) - psi(s0))


def _check_actuator_law(p: HeliostatProperties) -> None:
    """The counts-to-angle law must give finite, distinct angles at both count limits."""
    for i, a in enumerate(p.actuators):
        with np.errstate(all="ignore"):
            args = [np.float64(a[k]) for k in ("increment", "initial_stroke_length", "offset", "pivot_radius",
                                                "initial_angle")]
            sign = 1.0 if a["clockwise_axis_movement"] == 0 else -1.0
            lo, hi = (_actuator_law(*args, sign, np.float64(a[k])) for k in ("min_increment", "max_increment"))
            slope = (hi - lo) / (np.float64(a["max_increment"]) - np.float64(a["min_increment"]))
        if not (np.isfinite(lo) and np.isfinite(hi) and np.isfinite(slope) and slope != 0):
            raise DataError(p.source, f"kinematics_properties.actuators[{i}]",
                            f"the actuator law gives no usable angle range over [min_increment, max_increment] "
                            f"(angles {lo!r} .. {hi!r} rad)")


def _flag_properties(props: list[HeliostatProperties], log: _Log) -> None:
    """Physics checks per heliostat and robust fleet-outlier flags (module docstring)."""
    n = len(props)
    if n == 0:
        return
    a = {
        k: np.array([[float(p.actuators[i][k]) for i in range(2)] for p in props])
        for k in ("increment", "initial_stroke_length", "offset", "pivot_radius", "initial_angle",
                  "min_increment", "max_increment", "clockwise_axis_movement")
    }
    sign = np.where(a["clockwise_axis_movement"] == 0, 1.0, -1.0)
    # Triangle feasibility over the count range (stroke is monotone in the counts).
    for end in ("min_increment", "max_increment"):
        stroke = a[end] / a["increment"] + a["initial_stroke_length"]
        lo = np.abs(a["offset"] - a["pivot_radius"])
        hi = a["offset"] + a["pivot_radius"]
        bad = (stroke < lo) | (stroke > hi)
        for h, i in zip(*np.nonzero(bad)):
            log.flag(props[h].source, f"kinematics_properties.actuators[{i}].initial_stroke_length",
                     f"stroke {stroke[h, i]:.4f} m at {end} = {int(a[end][h, i])} lies outside the actuator "
                     f"triangle [{lo[h, i]:.4f}, {hi[h, i]:.4f}] m (law of cosines saturates)")
    # Majority direction of motion.
    for i in range(2):
        vals = a["clockwise_axis_movement"][:, i]
        cnt = collections.Counter(vals.tolist())
        mode, k = cnt.most_common(1)[0]
        if n >= _MIN_FLEET_FOR_OUTLIERS and 2 * k > n:
            for h in np.nonzero(vals != mode)[0]:
                log.flag(props[h].source, f"kinematics_properties.actuators[{i}].clockwise_axis_movement",
                         f"{int(vals[h])} where {k} of {n} heliostats have {int(mode)}")
    if n < _MIN_FLEET_FOR_OUTLIERS:
        log.notes.append(f"actuator outlier check not run: {n} heliostat(s) (needs {_MIN_FLEET_FOR_OUTLIERS})")
        return
    span = np.abs(
        _actuator_law(a["increment"], a["initial_stroke_length"], a["offset"], a["pivot_radius"],
                      a["initial_angle"], sign, a["max_increment"])
        - _actuator_law(a["increment"], a["initial_stroke_length"], a["offset"], a["pivot_radius"],
                        a["initial_angle"], sign, a["min_increment"])
    )
    checks: list[tuple[str, np.ndarray, np.ndarray, str]] = []  # (field, values (n,), scale (), unit)
    for i in range(2):
        for k, unit in (("increment", "counts/m"), ("initial_stroke_length", "m"), ("offset", "m"),
                        ("pivot_radius", "m")):
            v = a[k][:, i]
            checks.append((f"kinematics_properties.actuators[{i}].{k}", v, abs(np.median(v)), unit))
        checks.append((f"kinematics_properties.actuators[{i}].initial_angle", a["initial_angle"][:, i],
                       np.median(span[:, i]), "rad"))
    width = np.median([p.width for p in props])
    for name, attr in (("joint_translation_{}_1", "joint_translation_1"),
                       ("joint_translation_{}_2", "joint_translation_2"),
                       ("concentrator_translation_{}", "concentrator_translation")):
        vals = np.array([getattr(p, attr) for p in props])
        for j, c in enumerate("enu"):
            checks.append((f"kinematics_properties.{name.format(c)}", vals[:, j], width, "m"))
    for field, v, scale, unit in checks:
        med = np.median(v)
        mad = np.median(np.abs(v - med))
        thr = OUTLIER_K * max(1.4826 * mad, OUTLIER_FLOOR * float(scale))
        for h in np.nonzero(np.abs(v - med) > thr)[0]:
            log.flag(props[h].source, field,
                     f"{v[h]:.6g} {unit} is far from the fleet median {med:.6g} "
                     f"(|dev| {abs(v[h] - med):.3g} > {thr:.3g} = {OUTLIER_K:g} x max(1.4826 MAD, "
                     f"{OUTLIER_FLOOR:g} x scale))")


def _flag_repeated_weather(records: Sequence[CalibrationRecord], file: str, log: _Log) -> None:
    """Flag weather tuples repeated over rows spanning more than an hour (forward fill)."""
    groups: dict[tuple, list[float]] = collections.defaultdict(list)
    for r in records:
        w = tuple(r.weather[k] for k in ("temperature", "wind_speed", "wind_direction", "dni", "humidity",
                                          "pressure"))
        if all(math.isfinite(x) for x in w) and r.datetime is not None:
            groups[w].append(datetime_to_unix(r.datetime))
    for w, ts in groups.items():
        hours = (max(ts) - min(ts)) / 3600.0
        if len(ts) >= 3 and hours > 1.0:
            log.flag(file, "weather",
                     f"identical weather (temperature, wind_speed, wind_direction, dni, humidity, pressure) "
                     f"= {w} on {len(ts)} rows spanning {hours:.1f} h: looks forward-filled")


def _f(x) -> Array:
    """A JAX array of JAX's default float dtype (float64 under ``jax_enable_x64``)."""
    return jax.device_put(np.asarray(x, dtype=np.float64))


def _bucket_rows(x) -> np.ndarray:
    """Pad axis 0 to :func:`bucket_size` with copies of row 0 (float64), so that the
    jitted kernels below compile once per bucket, not once per fleet shape."""
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    return np.concatenate([x, np.repeat(x[:1], bucket_size(n) - n, axis=0)])


_enu_kernel = jax.jit(wgs84_to_enu)
_sun_kernel = jax.jit(lambda az, el: sun_direction(jnp.deg2rad(az), jnp.deg2rad(el)))
_geometry_kernel = jax.jit(HeliostatGeometry.build)
_targets_kernel = jax.jit(jax.vmap(TargetPlane.from_corners))


def _assemble(
    tower: TowerFile,
    properties: Sequence[HeliostatProperties],
    records: Sequence[CalibrationRecord],
    *,
    centroid: str,
    origin,
    log: _Log,
    validate: bool,
) -> Fleet:
    _check_centroid(centroid)
    planar = tower.planar_target_names
    tindex = {name: i for i, name in enumerate(planar)}
    origin_lla = tower.origin_lla if origin is None else tuple(float(x) for x in origin)
    if len(origin_lla) != 3 or not all(math.isfinite(x) for x in origin_lla):
        raise ValueError(f"origin must be 3 finite numbers [lat_deg, lon_deg, alt_m], got {origin!r}")

    props_by_id: dict[str, HeliostatProperties] = {}
    for p in sorted(properties, key=lambda p: p.heliostat_id):
        try:
            if validate:
                p = validate_properties(p)
            _check_actuator_law(p)
            if p.heliostat_id in props_by_id:
                raise DataError(p.source, None, f"second properties entry for heliostat {p.heliostat_id!r} "
                                                f"(first: {props_by_id[p.heliostat_id].source})")
        except DataError as e:
            log.skip(e, heliostats=1)
            continue
        props_by_id[p.heliostat_id] = p

    by_h: dict[str, list[CalibrationRecord]] = collections.defaultdict(list)
    for r in records:
        if not isinstance(r.heliostat_id, str) or not r.heliostat_id:
            log.skip_record(DataError(getattr(r, "source", None), "heliostat_id",
                                      f"must be a non-empty string, got {r.heliostat_id!r}"))
            continue
        by_h[r.heliostat_id].append(r)
    for hid in sorted(set(by_h) - set(props_by_id), key=str):
        rs = by_h[hid]
        log.skip(DataError(_common_dir([r.source for r in rs]), "heliostat_id",
                           f"{len(rs)} calibration record(s) of heliostat {hid!r} skipped: no properties file"),
                 records=len(rs), heliostats=1)

    ids = tuple(sorted(props_by_id))
    if not ids:
        rep = log.report()
        raise DataError(log.source, None, "no heliostat could be loaded\n" + rep.format())
    per_h: list[list[CalibrationRecord]] = []
    per_t: list[list[float]] = []
    n_fallback = 0
    for hid in ids:
        props = props_by_id[hid]
        good: list[CalibrationRecord] = []
        seen: set[int] = set()
        for r in by_h.get(hid, []):
            try:
                if validate:
                    r = validate_record(r)
                check_record_context(r, tower, props)
                if centroid == "helios" and r.focal_spot_helios is None:
                    raise DataError(r.source, "focal_spot.HeliOS", "missing (centroid='helios' uses HeliOS only)")
                if r.record_id in seen:
                    raise DataError(r.source, "record_id", f"duplicate record id {r.record_id} of {hid!r}")
            except DataError as e:
                log.skip_record(e)
                continue
            seen.add(r.record_id)
            good.append(r)
        times = [math.nan if r.datetime is None else datetime_to_unix(r.datetime) for r in good]
        order = _chronological(good, times)
        per_h.append([good[k] for k in order])
        per_t.append([times[k] for k in order])
        if not good:
            log.flag(props.source, None, f"heliostat {hid!r} has no valid calibration record (kept, all masked)")

    h = len(ids)
    m = max(1, max(len(rs) for rs in per_h))
    counts = np.zeros((h, m, 2))
    az = np.zeros((h, m))
    el = np.zeros((h, m))
    spot_lla = np.zeros((h, m, 3))
    tidx = np.zeros((h, m), np.int32)
    rid = np.full((h, m), -1, np.int32)
    utime = np.full((h, m), np.nan)
    weather = np.full((h, m, 3), np.nan)  # temperature, wind_speed, wind_direction (deg)
    mask = np.zeros((h, m), bool)
    n_no_time = n_weather = 0
    for i, (rs, ts) in enumerate(zip(per_h, per_t)):
        for j, (r, t) in enumerate(zip(rs, ts)):
            counts[i, j] = (r.axis_1_counts, r.axis_2_counts)
            az[i, j], el[i, j] = r.sun_azimuth_deg, r.sun_elevation_deg
            if centroid == "utis" and r.focal_spot_utis is not None:
                spot_lla[i, j] = r.focal_spot_utis
            else:
                spot_lla[i, j] = r.focal_spot_helios
                n_fallback += centroid == "utis"
            tidx[i, j] = tindex[r.target_name]
            rid[i, j] = r.record_id
            utime[i, j] = t
            weather[i, j] = (r.weather["temperature"], r.weather["wind_speed"], r.weather["wind_direction"])
            mask[i, j] = True
            if not math.isfinite(t):
                n_no_time += 1
                log.flag(r.source, "datetime", "no timestamp: time unknown (NaN), record kept")
            n_weather += any(not math.isnan(v) for v in r.weather.values())

    approach = _approach(counts, mask)
    n_valid = mask.sum(1)
    # Heliostats without records: one synthetic slot (mid-range counts, sun south at 45 deg).
    for i in np.nonzero(n_valid == 0)[0]:
        acts = props_by_id[ids[i]].actuators
        counts[i, 0] = [round((a["min_increment"] + a["max_increment"]) / 2) for a in acts]
        az[i, 0], el[i, 0] = 0.0, 45.0
    # Padded slots copy the first valid record (slot 0).
    pad = ~mask & (np.arange(m)[None, :] > 0)
    for arr in (counts, az, el, spot_lla, tidx, utime, weather, approach):
        arr[pad] = np.broadcast_to(arr[:, :1], arr.shape)[pad]

    pos_lla = np.array([props_by_id[k].position_lla for k in ids])
    corners_lla = np.array([[tower.targets[t].points[c] for c in CORNERS] for t in planar])  # (T, 4, 3)
    n_t = len(planar)
    # Geodesy in float64 on one flat, bucketed batch (one compilation per bucket).
    flat = np.concatenate([pos_lla, spot_lla.reshape(-1, 3), corners_lla.reshape(-1, 3)])
    with jax.enable_x64(True):
        enu = np.array(_enu_kernel(_bucket_rows(flat), np.asarray(origin_lla, np.float64)))[: len(flat)]
        sun = np.asarray(_sun_kernel(_bucket_rows(az.reshape(-1)), _bucket_rows(el.reshape(-1))))
    sun = sun[: h * m].reshape(h, m, 3)
    pos_enu = enu[:h]
    spot_enu = enu[h : h + h * m].reshape(h, m, 3)
    corners_enu = enu[h + h * m :].reshape(n_t, 4, 3)
    for k, name in enumerate(planar):
        ul, ur, ll, lr = corners_enu[k]
        width = np.linalg.norm((ur + lr) / 2 - (ul + ll) / 2)
        height = np.linalg.norm((ul + ur) / 2 - (ll + lr) / 2)
        if not (width > 1e-3 and height > 1e-3):
            raise DataError(tower.source, f"{name}.coordinates",
                            f"degenerate target corners (width {width:.3g} m, height {height:.3g} m)")
    centres = corners_enu.mean(axis=1)
    for i in np.nonzero(n_valid == 0)[0]:
        spot_enu[i] = centres[0]

    acts = {
        k: np.array([[float(props_by_id[hid].actuators[i][k]) for i in range(2)] for hid in ids])
        for k in ("increment", "initial_stroke_length", "offset", "pivot_radius", "initial_angle",
                  "min_increment", "max_increment", "clockwise_axis_movement")
    }
    actuators = LinearActuators(
        increment=_bucket_rows(acts["increment"]),
        initial_stroke_length=_bucket_rows(acts["initial_stroke_length"]),
        offset=_bucket_rows(acts["offset"]),
        pivot_radius=_bucket_rows(acts["pivot_radius"]),
        initial_angle=_bucket_rows(acts["initial_angle"]),
        sign=_bucket_rows(np.where(acts["clockwise_axis_movement"] == 0, 1.0, -1.0)),
        min_counts=_bucket_rows(acts["min_increment"]),
        max_counts=_bucket_rows(acts["max_increment"]),
    )
    with jax.enable_x64(True):
        geometry = _geometry_kernel(
            _bucket_rows(pos_enu),
            actuators,
            _bucket_rows(np.array([props_by_id[k].joint_translation_1 for k in ids])),
            _bucket_rows(np.array([props_by_id[k].joint_translation_2 for k in ids])),
            _bucket_rows(np.array([props_by_id[k].concentrator_translation for k in ids])),
        )
        targets = _targets_kernel(*(corners_enu[:, c] for c in range(4)))
    geometry = jax.tree.map(lambda x: _f(np.asarray(x)[:h]), geometry)
    targets = jax.tree.map(lambda x: _f(np.asarray(x)), targets)
    context = RecordContext(
        sun=_f(sun),
        unix_time=_f(utime),
        temperature=_f(weather[..., 0]),
        wind_speed=_f(weather[..., 1]),
        wind_direction=_f(np.deg2rad(weather[..., 2])),
        approach=_f(approach),
    )
    _flag_properties([props_by_id[k] for k in ids], log)
    report = log.report(
        records_loaded=int(mask.sum()),
        heliostats_loaded=h,
        records_without_time=n_no_time,
        records_with_weather=n_weather,
        centroid_fallbacks=n_fallback,
    )
    return Fleet(
        geometry=geometry,
        counts=_f(counts),
        context=context,
        focal_spot=_f(spot_enu),
        target_index=jax.device_put(tidx),
        record_id=jax.device_put(rid),
        mask=jax.device_put(mask),
        targets=targets,
        origin_lla=_f(origin_lla),
        ids=ids,
        target_names=planar,
        report=report,
    )


def records_to_fleet(
    tower: TowerFile,
    properties: Sequence[HeliostatProperties],
    records: Sequence[CalibrationRecord],
    *,
    centroid: Centroid = "utis",
    origin=None,
    strict: bool = False,
    source: str = "<records>",
) -> Fleet:
    """Assemble raw records into a :class:`Fleet` (the step shared by
    :func:`load_paint_directory`, :func:`load_weather_csv_fleet` and the simulator).

    Every property and record is validated as the readers would (so in-memory
    records from a simulator get the same checks); a bad one is skipped and
    reported (or raised with ``strict``). See the module docstring for ordering,
    padding and flags.

    Args:
        tower: the tower file (targets, ENU origin).
        properties: one per heliostat.
        records: calibration records of any of those heliostats.
        centroid: ``"utis"`` (UTIS, HeliOS where UTIS is missing) or ``"helios"``.
        origin: WGS84 ``[lat_deg, lon_deg, alt_m]`` overriding the tower file's
            plant coordinates as ENU origin.
        strict: raise the first :class:`DataError` instead of skipping.
        source: name of the input in the report.

    Returns:
        The fleet, unpadded (``M`` = most records of a heliostat, at least 1).

    Raises:
        DataError: (``strict``) the first bad input; always when no heliostat is left.
        ValueError: for an unknown ``centroid`` or a malformed ``origin``.
    """
    _check_centroid(centroid)
    log = _Log(source, strict, centroid)
    return _assemble(tower, properties, records, centroid=centroid, origin=origin, log=log, validate=True)


# ======================================================================================
# Loaders
# ======================================================================================


def load_paint_directory(
    path: str | os.PathLike | None = None,
    *,
    centroid: Centroid = "utis",
    heliostats: Iterable[str] | None = None,
    strict: bool = False,
    origin=None,
) -> Fleet:
    """Load a PAINT download directory into a :class:`Fleet`.

    Reads ``*-tower-measurements.json`` (exactly one; required),
    ``calibration-timestamps.json`` (optional: without it every time is NaN),
    ``calibration-with-weather.csv`` (optional: weather joined by
    ``(heliostat_id, sample_id == record id)``; its other rows are not records
    here) and every top-level heliostat folder ``<H>/Properties``,
    ``<H>/Calibration`` (other folders, such as ``flux-samples``, are ignored).

    One bad record, properties file or heliostat never spoils the others: it is
    skipped and listed in ``fleet.report`` with file, field and reason; the
    records of a heliostat without (valid) properties are skipped with it.

    Args:
        path: the directory; default: :func:`default_data_dir` (embedded data).
        centroid: ``"utis"`` (default; HeliOS where UTIS is missing/null) or ``"helios"``.
        heliostats: ids to load (default: all); others are not read.
        strict: raise the first :class:`DataError` instead of skipping.
        origin: WGS84 ENU origin overriding the tower file's plant coordinates.

    Raises:
        DataError: a missing/invalid tower file or no loadable heliostat (always);
            any bad input when ``strict``.
    """
    _check_centroid(centroid)
    root = default_data_dir() if path is None else Path(path)
    if not root.is_dir():
        raise DataError(root, None, "not a directory")
    log = _Log(str(root), strict, centroid)
    towers = sorted(root.glob("*" + TOWER_FILE_SUFFIX))
    if len(towers) != 1:
        raise DataError(root, None, f"expected one *{TOWER_FILE_SUFFIX}, found {len(towers)}")
    log.files_seen += 1
    tower = read_tower(towers[0])

    timestamps: Mapping = {}
    ts_path = root / TIMESTAMPS_FILE
    if ts_path.is_file():
        log.files_seen += 1
        try:
            timestamps = read_timestamps(ts_path, on_error=log.skip_entry)
        except DataError as e:
            log.skip(e)
    else:
        log.notes.append(f"no {TIMESTAMPS_FILE}: every record's time is unknown")

    weather: dict[tuple[str, int], dict[str, float]] = {}
    csv_path = root / WEATHER_CSV_FILE
    if csv_path.is_file():
        log.files_seen += 1
        try:
            rows = read_weather_csv(csv_path, on_error=log.skip_entry)
        except DataError as e:
            log.skip(e)
            rows = ()
        weather = {(r.heliostat_id, r.record_id): r.weather for r in rows}
        _flag_repeated_weather(rows, str(csv_path), log)

    dirs = sorted(d for d in root.iterdir() if d.is_dir() and ((d / "Properties").is_dir() or
                                                                  (d / "Calibration").is_dir()))
    if heliostats is not None:
        wanted = set(heliostats)
        for hid in sorted(wanted - {d.name for d in dirs}):
            log.skip(DataError(root / hid, None, f"heliostat {hid!r} requested but not in the directory"),
                     heliostats=1)
        dirs = [d for d in dirs if d.name in wanted]

    properties: list[HeliostatProperties] = []
    records: list[CalibrationRecord] = []
    for d in dirs:
        hid = d.name
        prop_files = sorted((d / "Properties").glob("*" + PROPERTIES_SUFFIX))
        cal_files = sorted((d / "Calibration").glob("*" + CALIBRATION_SUFFIX))
        log.files_seen += len(prop_files) + len(cal_files)
        expected = heliostat_properties_path(root, hid)
        try:
            if not prop_files:
                if not cal_files:
                    continue
                raise DataError(expected, None, f"missing: {len(cal_files)} calibration record(s) of heliostat "
                                                f"{hid!r} have no properties file")
            if len(prop_files) > 1 or prop_files[0].name != expected.name:
                raise DataError(d / "Properties", None,
                                f"expected exactly {expected.name}, found {[p.name for p in prop_files]}")
            props = read_heliostat_properties(prop_files[0], heliostat_id=hid)
        except DataError as e:
            log.skip(e, records=len(cal_files), heliostats=1)
            if prop_files and cal_files:
                log.skipped.append(ReportEntry(str(d / "Calibration"), None,
                                               f"{len(cal_files)} calibration record(s) skipped with heliostat "
                                               f"{hid!r} (bad properties file)"))
            continue
        properties.append(props)
        for cf in cal_files:
            try:
                records.append(read_calibration_record(cf, heliostat_id=hid, timestamps=timestamps,
                                                       weather=weather, tower=tower, properties=props))
            except DataError as e:
                log.skip_record(e)
    return _assemble(tower, properties, records, centroid=centroid, origin=origin, log=log, validate=False)


def load_weather_csv_fleet(
    csv_path: str | os.PathLike,
    tower_path: str | os.PathLike,
    properties_dir: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
    *,
    centroid: Centroid = "utis",
    heliostats: Iterable[str] | None = None,
    strict: bool = False,
    origin=None,
) -> Fleet:
    """Load the CSV form (``calibration-with-weather.csv``): each row is a record
    (HeliOS centroid, time and weather from the row).

    Heliostat properties are looked up as ``**/Properties/<H>-heliostat-properties.json``
    anywhere under ``properties_dir`` (one directory or several; default: the CSV's
    directory), the shallowest first; heliostats without one are skipped and
    reported (one entry per heliostat). Only the properties of heliostats present
    in the CSV are read.

    Args:
        csv_path: the CSV file.
        tower_path: the tower file (targets and ENU origin).
        properties_dir: where to look for properties files.
        centroid: as :func:`load_paint_directory` (CSV rows carry HeliOS only, so
            ``"utis"`` falls back to HeliOS for every row).
        heliostats: ids to load (default: all in the CSV).
        strict: raise the first :class:`DataError` instead of skipping.
        origin: WGS84 ENU origin overriding the tower file's.
    """
    _check_centroid(centroid)
    log = _Log(str(csv_path), strict, centroid)
    tower = read_tower(tower_path)
    log.files_seen += 2
    rows = read_weather_csv(csv_path, on_error=log.skip_record)
    if heliostats is not None:
        wanted = set(heliostats)
        for hid in sorted(wanted - {r.heliostat_id for r in rows}):
            log.skip(DataError(csv_path, "heliostat_id", f"heliostat {hid!r} requested but not in the CSV"),
                     heliostats=1)
        rows = tuple(r for r in rows if r.heliostat_id in wanted)
    _flag_repeated_weather(rows, str(csv_path), log)
    if properties_dir is None:
        dirs = [Path(csv_path).parent]
    elif isinstance(properties_dir, (str, os.PathLike)):
        dirs = [Path(properties_dir)]
    else:
        dirs = [Path(p) for p in properties_dir]
    needed = {r.heliostat_id for r in rows}
    found: dict[str, list[Path]] = collections.defaultdict(list)
    for d in dirs:
        hits = sorted(d.glob("**/Properties/*" + PROPERTIES_SUFFIX), key=lambda p: (len(p.parts), str(p)))
        for p in hits:
            hid = p.name[: -len(PROPERTIES_SUFFIX)]
            if hid in needed:
                found[hid].append(p)
    properties = []
    for hid in sorted(found):
        first, *others = found[hid]
        for o in others:
            log.flag(str(o), None, f"another properties file of {hid!r}; using {first}")
        log.files_seen += 1
        try:
            properties.append(read_heliostat_properties(first, heliostat_id=hid))
        except DataError as e:
            log.skip(e, heliostats=1)
            bad = [r for r in rows if r.heliostat_id == hid]
            log.skipped.append(ReportEntry(str(csv_path), "heliostat_id",
                                           f"{len(bad)} row(s) of heliostat {hid!r} skipped (bad properties file)"))
            log.records_skipped += len(bad)
            rows = tuple(r for r in rows if r.heliostat_id != hid)
    return _assemble(tower, properties, rows, centroid=centroid, origin=origin, log=log, validate=False)


def fleet_from_arrays(
    geometry: HeliostatGeometry,
    counts: Float[Array, "H M 2"],
    context: RecordContext,
    focal_spot: Float[Array, "H M 3"],
    mask: Bool[Array, "H M"] | None = None,
    *,
    ids: Sequence[str] | None = None,
    origin_lla: Sequence[float] = (50.913421122592574, 6.387824755874856, 87.0),
) -> Fleet:
    """A :class:`Fleet` from arrays of one's own (simulations, other data sources):
    batched geometry ``(H, ...)``, counts ``(H, M, 2)``, contexts ``(H, M)``,
    focal spots ``(H, M, 3)`` ENU m, and a mask (default: every finite record).
    Ids default to ``H000, H001, ...``; there are no calibration targets."""
    counts = jnp.asarray(counts)
    h, m = counts.shape[:2]
    focal_spot = jnp.asarray(focal_spot, counts.dtype)
    if mask is None:
        mask = jnp.all(jnp.isfinite(counts), -1) & jnp.all(jnp.isfinite(focal_spot), -1)
    targets = jax.tree.map(lambda x: jnp.zeros((0,) + jnp.shape(x), jnp.asarray(x).dtype), _unit_target(counts.dtype))
    return Fleet(
        geometry=geometry,
        counts=counts,
        context=context,
        focal_spot=focal_spot,
        target_index=jnp.full((h, m), -1, jnp.int32),
        record_id=jnp.asarray(np.arange(h * m).reshape(h, m), jnp.int64),
        mask=jnp.asarray(mask, bool),
        targets=targets,
        origin_lla=jnp.asarray(origin_lla, counts.dtype),
        ids=tuple(ids) if ids is not None else tuple(f"H{i:03d}" for i in range(h)),
        target_names=(),
        report=LoadReport(source="<arrays>", records_loaded=int(np.sum(np.asarray(mask))), heliostats_loaded=h),
    )


def _unit_target(dtype: typing.Any) -> TargetPlane:
    corners = [jnp.asarray(c, dtype) for c in ([-1.0, 0, 1], [1.0, 0, 1], [-1.0, 0, -1], [1.0, 0, -1])]
    return TargetPlane.from_corners(*corners)
