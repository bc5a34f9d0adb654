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

import collections.abc
import dataclasses
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, Real

from ._geometry import TargetPlane, angle_between, check_unit_vectors
from ._heliostat import HeliostatGeometry, RecordContext
from ._io import heliostat_id_problem, shown_value
from ._limits import MAX_SYNTHETIC_HELIOSTATS, MAX_SYNTHETIC_RECORDS, count_problem

__all__ = [
    "OUTLIER_FLOOR",
    "OUTLIER_K",
    "Fleet",
    "HeliostatRecords",
    "LoadReport",
    "ReportEntry",
    "bucket_size",
    "fleet_from_arrays",
    "fleet_subset",
    "pad_fleet",
    "records_among",
]

Centroid = Literal["utis", "helios"]
CENTROIDS = ("utis", "helios")
"""The focal-spot centroids a load can select (see :data:`Centroid`)."""

OUTLIER_K = 5.0
"""Robust outlier threshold in (robust) standard deviations."""
OUTLIER_FLOOR = 0.01
"""Relative floor of the robust scale (fraction of the quantity's natural scale)."""
MIN_FLEET_FOR_OUTLIERS = 3
"""Fewest heliostats for the load's fleet-wide actuator outlier check."""


# ======================================================================================
# Load report
# ======================================================================================


class ReportEntry(NamedTuple):
    """One skipped or flagged input: the file, the dotted field (or None), why, and
    whether a whole heliostat was skipped with it."""

    file: str
    field: str | None
    reason: str
    heliostat: bool = False


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


@typing.final
class HeliostatRecords(eqx.Module):
    """One heliostat of a :class:`Fleet` (:meth:`Fleet.heliostat`): the fleet's
    per-heliostat arrays without the leading axis (``M`` records)."""

    geometry: HeliostatGeometry
    counts: Float[Array, "M 2"]
    context: RecordContext
    focal_spot: Float[Array, "M 3"]
    record_id: Int[Array, " M"]
    mask: Bool[Array, " M"]
    id: str = eqx.field(static=True)

    @property
    def target_index(self) -> Int[Array, " M"]:
        """``(M,)`` the records' targets, ``context.target`` (-1 unknown)."""
        return self.context.target


@typing.final
class Fleet(eqx.Module):
    """Calibration records of ``H`` heliostats, padded to ``M`` records each.

    Attributes:
        geometry: batched :class:`HeliostatGeometry` (leading axis ``H``; ENU m, rad).
        counts: ``(H, M, 2)`` motor counts (axis 1, axis 2), float.
        context: batched :class:`RecordContext` ``(H, M, ...)``: ``sun`` unit ENU
            vectors from the recorded azimuth/elevation, ``unix_time`` s (NaN unknown),
            ``temperature`` deg C, ``wind_speed`` m/s, ``wind_direction`` rad (NaN
            unknown), ``approach`` ``(H, M, 2)`` in {-1, 0, +1}, ``target``
            ``(H, M)`` int, the record's calibration target: index into ``targets`` /
            ``target_names``, -1 unknown (also :attr:`target_index`).
        focal_spot: ``(H, M, 3)`` ENU m, the selected centroid.
        record_id: ``(H, M)`` PAINT record id, -1 for padding.
        mask: ``(H, M)`` True for valid records.
        targets: batched :class:`TargetPlane` ``(T,)``, the tower file's planar targets.
        origin_lla: ``(3,)`` WGS84 ``[lat_deg, lon_deg, alt_m]`` of the ENU origin.
        ids: heliostat ids (``""`` for padding heliostats); static.
        target_names: names of ``targets``; static.
        report: the :class:`LoadReport`; static.

    ``ids``, ``target_names`` and ``report`` are static metadata, outside the traced
    arrays. heliojax's compiled programs (:func:`heliojax.fit`, the evaluations)
    take the fleet's arrays, never the Fleet itself, so fleets that differ only in
    their metadata share one compiled program. A user who jits a function of a whole
    Fleet keys that function's cache on the metadata: pass the arrays instead.
    """

    geometry: HeliostatGeometry
    counts: Float[Array, "H M 2"]
    context: RecordContext
    focal_spot: Float[Array, "H M 3"]
    record_id: Int[Array, "H M"]
    mask: Bool[Array, "H M"]
    targets: TargetPlane
    origin_lla: Float[Array, "3"]
    ids: tuple[str, ...] = eqx.field(static=True)
    target_names: tuple[str, ...] = eqx.field(static=True)
    report: LoadReport = eqx.field(static=True)

    def __check_init__(self):
        shape = jnp.shape(self.mask)
        dtype = getattr(self.mask, "dtype", None)
        if len(shape) != 2 or dtype != np.dtype(bool):
            # a float mask had failed in JAX's `and` inside the fit, a mask of one axis as
            # "not enough values to unpack"
            raise ValueError(
                f"Fleet.mask has shape {tuple(shape)} and dtype {dtype}; expected booleans (H, M), True for the "
                "valid records (heliojax.fleet_from_arrays takes 0/1 integers too)"
            )
        h, m = shape
        checks = {
            "counts": (jnp.shape(self.counts), (h, m, 2)),
            "focal_spot": (jnp.shape(self.focal_spot), (h, m, 3)),
            "context.target": (jnp.shape(self.context.target), (h, m)),
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
        named = [i for i in self.ids if i != ""]  # "": a padding heliostat
        if not all(isinstance(i, str) for i in named):
            other = next(i for i in named if not isinstance(i, str))
            raise ValueError(f"Fleet.ids: heliostat ids are strings, got {shown_value(other)} ({type(other).__name__})")
        if len(set(named)) != len(named):  # two heliostats of one id: each report row, each aim ambiguous
            twice = next(x for k, x in enumerate(named) if x in named[:k])
            raise ValueError(f"Fleet.ids: heliostat id {shown_value(twice)} is listed twice")
        if len(self.target_names) != jnp.shape(self.targets.centre)[0]:
            raise ValueError("Fleet.target_names does not match targets")

    @property
    def target_index(self) -> Int[Array, "H M"]:
        """``(H, M)`` each record's target, an index into ``targets`` /
        ``target_names`` (-1 unknown): the contexts' ``target`` (one array, not a copy)."""
        return self.context.target

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
        """The arrays of heliostat ``i`` (position, or id) without the leading axis
        (TypeError for anything else: ``True`` had been heliostat 1, 1.7 heliostat 1)."""
        if isinstance(i, str):
            i = self.index(i)
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)):
            raise TypeError(f"Fleet.heliostat: expected a heliostat position (int) or id (str), got {i!r}"[:200])
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
            record_id=self.record_id[i],
            mask=self.mask[i],
            id=self.ids[i],
        )


_PER_HELIOSTAT = ("geometry", "counts", "context", "focal_spot", "record_id", "mask")


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
    return jnp if any(isinstance(x, jax.core.Tracer) for x in leaves) else np  # pyright: ignore[reportAttributeAccessIssue]


def _to_jax(tree):
    """numpy leaves -> device arrays without a compilation (tracers pass through)."""
    return jax.tree.map(
        lambda x: x if isinstance(x, jax.core.Tracer) else jax.device_put(x),  # pyright: ignore[reportAttributeAccessIssue]
        tree,
    )


def pad_fleet(fleet: Fleet, n_heliostats: int | None = None, n_records: int | None = None) -> Fleet:
    """Pad a fleet to ``(n_heliostats, n_records)`` (default: :func:`bucket_size`
    of the current sizes).

    Padded record slots copy the heliostat's first valid record (slot 0 when none),
    with ``mask`` False and ``record_id`` -1; padding heliostats copy heliostat 0
    with an all-False mask, ``record_id`` -1 and id ``""``. Values in the valid
    region are unchanged. Shapes change, so call it outside ``jit`` (it works under
    tracing too, but then compiles per shape).

    Raises:
        ValueError: a requested size that is no whole number (8.5 had been read as 8,
            ``True`` as 1, ``"16"`` as 16), beyond :data:`heliojax._limits.MAX_SYNTHETIC_HELIOSTATS`
            heliostats or :data:`heliojax._limits.MAX_SYNTHETIC_RECORDS` records each, or
            smaller than the fleet's.
    """
    h, m = fleet.n_heliostats, fleet.n_records
    for name, value, limit in (
        ("n_heliostats", n_heliostats, max(h, MAX_SYNTHETIC_HELIOSTATS)),
        ("n_records", n_records, max(m, MAX_SYNTHETIC_RECORDS)),
    ):
        problem = None if value is None else count_problem(value, limit, minimum=0)
        if problem is not None:
            raise ValueError(f"pad_fleet: {name} {problem}")
    nh = bucket_size(h) if n_heliostats is None else int(n_heliostats)
    nm = bucket_size(m) if n_records is None else int(n_records)
    if nh < h or nm < m:
        raise ValueError(f"cannot pad a fleet of shape ({h}, {m}) to ({nh}, {nm})")
    xp = _backend(fleet)
    rec = {k: getattr(fleet, k) for k in ("counts", "context", "focal_spot")}
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
    the record axis, targets and report are kept.

    Args:
        fleet: the fleet.
        indices: one position (int, negative from the end) or id (str), or a
            sequence / integer array of them.

    Raises:
        TypeError: an index that is neither an integer nor an id (a bool, 1.5, a
            boolean mask: use ``np.flatnonzero(mask)``).
        ValueError: no heliostat selected (empty ``indices``), an id not in the fleet, a
            heliostat selected twice.
        IndexError: a position out of range.
    """
    if isinstance(indices, np.ndarray) and indices.dtype.kind not in "iuUSO":
        raise TypeError(
            f"fleet_subset: indices has dtype {indices.dtype}; expected integer positions or heliostat ids "
            "(a boolean mask: np.flatnonzero(mask))"
        )
    if isinstance(indices, np.ndarray):
        items: list = [indices.item()] if indices.ndim == 0 else list(indices)
    elif isinstance(indices, (str, bytes)) or not isinstance(indices, collections.abc.Iterable):
        items = [indices]
    else:
        items = list(indices)
    if not items:
        raise ValueError(f"fleet_subset: no heliostat selected (indices is empty; the fleet has {fleet.n_heliostats})")
    idx = []
    for i in items:
        if isinstance(i, (str, np.str_)):
            idx.append(fleet.index(str(i)))
        elif isinstance(i, (int, np.integer)) and not isinstance(i, (bool, np.bool_)):
            idx.append(int(i))
        else:
            raise TypeError(
                f"fleet_subset: index {i!r} ({type(i).__name__}); expected an integer position or a heliostat id"
            )
    for i in idx:
        if not -fleet.n_heliostats <= i < fleet.n_heliostats:
            raise IndexError(f"heliostat index {i} out of range for {fleet.n_heliostats}")
    # a repeated heliostat: two fits of one, counted twice (all selections at once)
    at = np.asarray(idx, dtype=np.int64) % fleet.n_heliostats
    _, first = np.unique(at, return_index=True)
    first_of = np.empty(fleet.n_heliostats, np.int64)
    first_of[at[first]] = first
    again = np.flatnonzero(first_of[at] < np.arange(at.size))
    if again.size:
        j = int(again[0])
        h = int(at[j])
        raise ValueError(
            f"fleet_subset: indices selects heliostat {h} ({fleet.ids[h]!r}) twice "
            f"({shown_value(items[int(first_of[h])])} and {shown_value(items[j])})"
        )
    xp = _backend(fleet)
    sel = np.asarray(idx, dtype=np.int64)
    take = lambda x: _to_jax(xp.asarray(x)[sel])  # noqa: E731
    return _replace(
        fleet,
        **{k: jax.tree.map(take, getattr(fleet, k)) for k in _PER_HELIOSTAT},
        ids=tuple(fleet.ids[i] for i in idx),
    )


def spots_off_target(fleet: Fleet) -> Bool[np.ndarray, "H M"]:
    """``(H, M)`` valid records whose focal spot lies farther from the centre of its
    record's target than the target's corners (half its diagonal): no spot on the
    target, as the loader flags it (the same rule, in ENU metres); False for padding
    and for records of an unknown target.

    A camera sees only its target, so such a spot is a wrong spot, target or survey,
    not a pointing error: :func:`heliojax.calibrate` leaves these records out of the
    fleet's statistics and does not aim with a heliostat that has mostly them.
    """
    index = np.asarray(fleet.target_index)
    n_targets = np.shape(fleet.targets.centre)[0]
    known = np.asarray(fleet.mask, bool) & (index >= 0) & (index < n_targets)
    if not known.any():  # no targets (a fleet of arrays): nothing to judge
        return known
    at = np.where(known, index, 0)
    centre = np.asarray(fleet.targets.centre)[at]
    reach = np.hypot(np.asarray(fleet.targets.half_width), np.asarray(fleet.targets.half_height))[at]
    distance = np.linalg.norm(np.asarray(fleet.focal_spot) - centre, axis=-1)
    return known & ~(distance <= reach)  # a NaN spot is off too


def spot_scatter_mrad(fleet: Fleet, mask: Bool[ArrayLike, "H M"] | None = None) -> Float[np.ndarray, " H"]:
    """``(H,)`` RMS per tangent component (mrad) of the angle, seen from each
    heliostat, between its records' focal spots and their targets' centres (the
    records of ``mask``, default the valid ones, with a known target); NaN where there
    is none. The residual scale of a model that puts every beam on the target centre:
    a fitted model whose noise is well above it predicts the spots worse than that."""
    index = np.asarray(fleet.target_index)
    n_targets = np.shape(fleet.targets.centre)[0]
    use = np.asarray(fleet.mask if mask is None else mask, bool) & (index >= 0) & (index < n_targets)
    centre = np.asarray(fleet.targets.centre)[np.where(use, index, 0)] if n_targets else np.zeros((*use.shape, 3))
    position = np.asarray(fleet.geometry.position)[:, None, :]
    angle = np.asarray(angle_between(np.asarray(fleet.focal_spot) - position, centre - position))
    use &= np.isfinite(angle)
    n = use.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, 1e3 * np.sqrt(np.sum(np.where(use, angle, 0.0) ** 2, axis=1) / (2 * n)), np.nan)


def records_among(
    ids: Sequence[str],
    record_id: Int[ArrayLike, "H M"],
    other_ids: Sequence[str],
    other_record_id: Int[ArrayLike, "G N"],
    other_picked: Bool[ArrayLike, "G N"],
) -> Bool[np.ndarray, "H M"]:
    """``(H, M)`` whether each record (heliostat ``ids[h]``, PAINT record id
    ``record_id[h, m]``) is one of the other fleet's picked records (the same heliostat id
    and record id; record ids below 2**31), all at once."""
    index = {h: i for i, h in enumerate(dict.fromkeys([*ids, *other_ids]))}

    def keys(names: Sequence[str], rid: ArrayLike) -> np.ndarray:
        # (heliostat, record id) as one integer
        rows = np.array([index[h] for h in names], np.int64).reshape(-1, 1)
        return (rows << 32) + np.asarray(rid, np.int64)

    picked = keys(other_ids, other_record_id)[np.asarray(other_picked, bool)]
    return np.isin(keys(ids, record_id), picked)


def fleet_from_arrays(
    geometry: HeliostatGeometry,
    counts: Real[ArrayLike, "H M 2"],
    context: RecordContext,
    focal_spot: Real[ArrayLike, "H M 3"],
    mask: Bool[ArrayLike, "H M"] | None = None,
    *,
    ids: Sequence[str] | None = None,
    origin_lla: Sequence[float] = (50.913421122592574, 6.387824755874856, 87.0),
) -> Fleet:
    """A :class:`Fleet` from arrays of one's own (simulations, other data sources):
    batched geometry ``(H, ...)``, counts ``(H, M, 2)``, contexts ``(H, M)``,
    focal spots ``(H, M, 3)`` ENU m, and a mask (default: every finite record).
    Ids default to ``H000, H001, ...``; there are no calibration targets (every
    context's ``target`` is set to -1, unknown). Counts, focal spots and the origin
    are converted to JAX's default float (float64 with ``jax_enable_x64``), whatever
    their own type: integer counts must not round the focal spots to whole metres.

    Raises:
        TypeError: ``geometry`` or ``context`` of another kind (None had failed as an
            AttributeError), an id that is no string.
        ValueError: an array whose shape is not the one above for the ``H, M`` of
            ``counts`` (each had failed in JAX's or NumPy's broadcasting, naming no
            argument); a mask that is not boolean (or 0/1 integers); an origin that is
            not a finite latitude, longitude, altitude; a used record's sun that is not
            a unit vector; ``ids`` not one per heliostat, an id listed twice, or one that
            is no heliostat id (:func:`heliojax._io.heliostat_id_problem`: ``""`` had made
            its heliostat a padding one, left out of every statistic; ``"a,b"`` is two in
            an option).
    """
    for name, value, kind in (("geometry", geometry, HeliostatGeometry), ("context", context, RecordContext)):
        if not isinstance(value, kind):
            got = type(value).__name__
            raise TypeError(f"fleet_from_arrays: {name}: expected a batched heliojax.{kind.__name__}, got {got}")
    h, m = (tuple(np.shape(counts)) + (0, 0))[:2]
    for name, got, want in (
        ("counts", np.shape(counts), (h, m, 2)),
        ("focal_spot", np.shape(focal_spot), (h, m, 3)),
        ("context.sun", jnp.shape(context.sun), (h, m, 3)),
        ("context.unix_time", jnp.shape(context.unix_time), (h, m)),
        ("geometry.position", jnp.shape(geometry.position), (h, 3)),
        ("mask", None if mask is None else np.shape(mask), (h, m)),
    ):
        if got is not None and tuple(got) != want:
            shown = "(H, M, 2): H heliostats x M records x 2 axes" if name == "counts" else f"{want}, as counts'"
            raise ValueError(f"fleet_from_arrays: {name} has shape {tuple(got)}; expected {shown}")
    dtype = jnp.result_type(float)  # float64 under jax_enable_x64
    counts = jnp.asarray(counts, dtype)
    if ids is not None:
        ids = [ids] if isinstance(ids, str) else list(ids)
        if len(ids) != h:
            raise ValueError(f"ids: {len(ids)} heliostat ids for the {h} heliostats of counts")
        for i in ids:
            if not isinstance(i, str):
                raise TypeError(f"ids: heliostat ids are strings, got {shown_value(i)} ({type(i).__name__})")
            problem = heliostat_id_problem(i)
            if problem is not None:
                raise ValueError(f"ids: {shown_value(i)} is no heliostat id: {problem}")
        if len(set(ids)) != len(ids):
            twice = next(x for k, x in enumerate(ids) if x in ids[:k])
            raise ValueError(f"ids: heliostat id {shown_value(twice)} is listed twice")
    context = eqx.tree_at(lambda c: c.target, context, jnp.full((h, m), -1, jnp.int32))
    focal_spot = jnp.asarray(focal_spot, dtype)
    origin = np.asarray(origin_lla, float)
    if origin.shape != (3,) or not np.isfinite(origin).all() or abs(origin[0]) > 90 or abs(origin[1]) > 180:
        raise ValueError(f"origin_lla: expected a WGS84 latitude, longitude (degrees) and altitude (m), got {origin}")
    if mask is not None and (np.asarray(mask).dtype.kind not in "biu" or not np.isin(np.asarray(mask), (0, 1)).all()):
        raise ValueError(f"mask: expected booleans (H, M), got {np.asarray(mask).dtype} values other than 0 and 1")
    if mask is None:
        mask = jnp.all(jnp.isfinite(counts), -1) & jnp.all(jnp.isfinite(focal_spot), -1)
    check_unit_vectors(context.sun, mask, "context.sun")
    targets = jax.tree.map(lambda x: jnp.zeros((0,) + jnp.shape(x), jnp.asarray(x).dtype), _unit_target(dtype))
    return Fleet(
        geometry=geometry,
        counts=counts,
        context=context,
        focal_spot=focal_spot,
        record_id=jnp.asarray(np.arange(h * m).reshape(h, m), jnp.int64),
        mask=jnp.asarray(mask, bool),
        targets=targets,
        origin_lla=jnp.asarray(origin_lla, dtype),
        ids=tuple(ids) if ids is not None else tuple(f"H{i:03d}" for i in range(h)),
        target_names=(),
        report=LoadReport(source="<arrays>", records_loaded=int(np.sum(np.asarray(mask))), heliostats_loaded=h),
    )


def _unit_target(dtype: typing.Any) -> TargetPlane:
    corners = [jnp.asarray(c, dtype) for c in ([-1.0, 0, 1], [1.0, 0, 1], [-1.0, 0, -1], [1.0, 0, -1])]
    return TargetPlane.from_corners(*corners)
