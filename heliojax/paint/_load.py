"""Loading a PAINT download directory (or the weather CSV form) into a :class:`heliojax.Fleet`:
parse every file, skip and report bad ones, flag suspicious values, assemble padded arrays."""

from __future__ import annotations

import collections
import dataclasses
import datetime as dt
import importlib.resources
import math
import os
import re
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import no_type_check

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from .._errors import DataError, few_names
from .._fleet import CENTROIDS, Centroid, Fleet, ReportEntry, bucket_size
from .._geometry import TargetPlane, sun_direction, wgs84_to_enu
from .._heliostat import HeliostatGeometry, LinearActuators, RecordContext
from .._io import check_path_argument, heliostat_id_problem, shown_value
from .._programs import cached_jit
from .._sun import datetime_to_unix, solar_position
from ._calibration import (
    check_record_context,
    heliostat_properties_path,
    read_calibration_record,
    spot_off_target,
    validate_record,
)
from ._common import (
    CALIBRATION_SUFFIX,
    CORNERS,
    MAX_HELIOSTAT_DISTANCE_M,
    MAX_HELIOSTAT_HEIGHT_M,
    MAX_SUN_GAP_DEG,
    PROPERTIES_SUFFIX,
    SUN_FLAG_DEG,
    TIMESTAMPS_FILE,
    TOWER_FILE_SUFFIX,
    WEATHER_CSV_FILE,
    CalibrationRecord,
    HeliostatProperties,
    TimestampEntry,
    TowerFile,
    _distance_m,
    _nan_weather,
    requested_heliostats,
)
from ._flags import (
    EARLIEST_RECORD_TIME,
    _check_actuator_law,
    _flag_properties,
    _flag_repeated_weather,
    _flag_weather_gaps,
    _Log,
)
from ._properties import read_heliostat_properties, validate_properties
from ._timestamps import METADATA_GLOB, read_metadata_times, read_timestamps
from ._tower import check_target_corners, read_tower
from ._weather import read_weather_csv


def default_data_dir() -> Path:
    """The embedded PAINT subset shipped with heliojax (``heliojax/data/paint``):
    5 heliostats of the Jülich tower (CDLA-Permissive-2.0, see its NOTICE)."""
    return Path(str(importlib.resources.files("heliojax") / "data" / "paint"))


# ======================================================================================
# Assembly
# ======================================================================================


def _check_centroid(centroid: str) -> None:
    if centroid not in CENTROIDS:
        raise ValueError(f"centroid must be one of {CENTROIDS}, got {centroid!r}")


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


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _measurement(r: CalibrationRecord) -> tuple:
    """What a measurement is made of: two records alike in all of it are copies."""
    return (
        r.datetime,
        r.axis_1_counts,
        r.axis_2_counts,
        r.target_name,
        r.sun_azimuth_deg,
        r.sun_elevation_deg,
        r.focal_spot_helios,
        r.focal_spot_utis,
    )


def _first_of_each_measurement(records: Iterable[CalibrationRecord]) -> dict[tuple, int]:
    """Measurement -> the lowest record id holding it (the one kept of identical copies)."""
    first: dict[tuple, int] = {}
    for r in records:
        try:
            key = _measurement(r)
            if key not in first or r.record_id < first[key]:
                first[key] = r.record_id
        except TypeError:  # an unvalidated record with unhashable parts: checked later
            continue
    return first


MAX_WEATHER_TIME_GAP_S = 1.0
"""A weather row whose time is farther than this from its record's time (from
``calibration-timestamps.json``; PAINT writes both from one source, equal to the second)
describes another moment: its weather is not used."""


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _weather_of_its_time(r: CalibrationRecord, row: CalibrationRecord | None, log: _Log) -> CalibrationRecord:
    """``r``, without the weather of ``row`` (its weather CSV row) when the row's time
    is not the record's (flagged)."""
    if row is None or r.datetime is None or row.datetime is None:
        return r
    gap = abs(datetime_to_unix(row.datetime) - datetime_to_unix(r.datetime))
    if not gap > MAX_WEATHER_TIME_GAP_S:
        return r
    log.flag(
        str(row.source),
        "timestamp",
        f"{row.datetime} is {gap:.6g} s from record {r.record_id}'s time {r.datetime} "
        f"({TIMESTAMPS_FILE}): weather of another moment, not used",
    )
    return dataclasses.replace(r, weather=_nan_weather())


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


def _f(x) -> Array:
    """A JAX array of JAX's default float dtype (float64 under ``jax_enable_x64``)."""
    return jax.device_put(np.asarray(x, dtype=np.float64))


def _bucket_rows(x) -> np.ndarray:
    """Pad axis 0 to :func:`bucket_size` with copies of row 0 (float64), so that the
    jitted kernels below compile once per bucket, not once per fleet shape."""
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    return np.concatenate([x, np.repeat(x[:1], bucket_size(n) - n, axis=0)])


def _sun_vectors(azimuth_deg, elevation_deg):
    return sun_direction(jnp.deg2rad(azimuth_deg), jnp.deg2rad(elevation_deg))


def _target_planes(*corners):
    return jax.vmap(TargetPlane.from_corners)(*corners)


def _sun_gap(unix_time, lla, azimuth_deg, elevation_deg):
    """Angle (deg) between the stored sun and the sun computed (SPA, with refraction) for
    the time at the position; and the computed azimuth and elevation (deg)."""
    pos = solar_position(unix_time, lla[:, 0], lla[:, 1], lla[:, 2])
    stored = _sun_vectors(azimuth_deg, elevation_deg)
    computed = pos.direction_enu()
    cross = jnp.linalg.norm(jnp.cross(stored, computed), axis=-1)
    gap = jnp.arctan2(cross, jnp.sum(stored * computed, axis=-1))
    return jnp.rad2deg(gap), jnp.rad2deg(pos.azimuth), jnp.rad2deg(pos.elevation)


# jitted once per shape bucket; traced programs kept across processes (heliojax._programs)
def _enu_and_suns(points_lla, origin_lla, azimuth_deg, elevation_deg):
    """:func:`wgs84_to_enu` of the points and :func:`_sun_vectors` of the suns: two
    independent computations in one program (one program to load, not two)."""
    return wgs84_to_enu(points_lla, origin_lla), _sun_vectors(azimuth_deg, elevation_deg)


def _geometry_and_targets(position, actuators, joint_1, joint_2, concentrator, ideal, corners):
    """:meth:`HeliostatGeometry.build` and :func:`_target_planes` of ``corners`` (a
    tuple): two independent computations in one program."""
    return HeliostatGeometry.build(position, actuators, joint_1, joint_2, concentrator, ideal), _target_planes(*corners)


# run once per load: compiled quickly (heliojax._xla_flags)
_enu_sun_kernel = cached_jit(_enu_and_suns, quick=True)
_geometry_targets_kernel = cached_jit(_geometry_and_targets, quick=True)
_sun_gap_kernel = cached_jit(_sun_gap, quick=True)
_SUN_CHUNK = 256


def _whole_hours_off(gap: np.ndarray, gaps) -> str:
    """Why most stored suns disagree with their times: if times shifted by whole hours
    (``gaps(shift_s)``, the gaps at the shifted times) fit nearly all, the shift of each
    record (PAINT before 3.0 converted times it took for Europe/Berlin local time to
    UTC, so they are 1 h (winter) or 2 h (summer) early; PAINT's changelog of 3.0.0), else
    the general question."""
    best = gap.copy()
    hours = np.zeros(gap.shape)
    for h in (-2.0, -1.0, 1.0, 2.0):
        g = gaps(3600.0 * h)[0]
        better = g < best
        best, hours = np.where(better, g, best), np.where(better, h, hours)
    fit = best <= MAX_SUN_GAP_DEG
    if fit.mean() < 0.95 or not (hours[fit] != 0).any():
        return "times in another zone, or suns from another model?"
    counts = ", ".join(
        f"{int(np.sum(hours[fit] == h))} by {h:+g} h" for h in (-2.0, -1.0, 1.0, 2.0) if np.any(hours[fit] == h)
    )
    return (
        f"the suns fit their times shifted by whole hours ({counts} of {gap.size}): times of another "
        "zone, e.g. PAINT before 3.0, whose times are 1-2 h early (Europe/Berlin local time converted as if UTC)."
    )


def _drop_sun_mismatches(
    goods: list[list[CalibrationRecord]], positions: Sequence, log: _Log
) -> list[list[CalibrationRecord]]:
    """Skip (and name) every timed record whose stored sun lies more than
    :data:`MAX_SUN_GAP_DEG` from the sun computed for its time at its heliostat
    (``positions[i]``, WGS84), flag those more than :data:`SUN_FLAG_DEG` from it: one
    batched solar-position call over all records. When most timed records disagree, the
    data set follows another convention: all are kept and one flag says so."""
    where = [(i, k) for i, rs in enumerate(goods) for k, r in enumerate(rs) if r.datetime is not None]
    if not where:
        return goods
    rs = [goods[i][k] for i, k in where]
    t = np.array([datetime_to_unix(r.datetime) for r in rs])  # pyright: ignore[reportArgumentType]
    lla = np.array([positions[i] for i, _ in where], dtype=np.float64)
    az = np.array([r.sun_azimuth_deg for r in rs], dtype=np.float64)
    el = np.array([r.sun_elevation_deg for r in rs], dtype=np.float64)
    n = len(rs)
    size = -(-n // _SUN_CHUNK) * _SUN_CHUNK  # one compiled shape for every fleet (SPA compiles slowly)

    def gaps(shift_s: float) -> tuple[np.ndarray, ...]:
        cols = [np.concatenate([x, np.repeat(x[:1], size - n, axis=0)]) for x in (t + shift_s, lla, az, el)]
        parts = []
        with jax.enable_x64(True):
            for a in range(0, size, _SUN_CHUNK):
                parts.append([np.asarray(x) for x in _sun_gap_kernel(*(c[a : a + _SUN_CHUNK] for c in cols))])
        return tuple(np.concatenate(x)[:n] for x in zip(*parts))

    gap, az_c, el_c = gaps(0.0)
    far = ~(gap <= MAX_SUN_GAP_DEG)
    if 2 * int(far.sum()) > n:
        # Most suns disagree with their times: a convention of the whole data set (times in
        # another zone, suns from another model), not a damaged record each: keep them all.
        j = int(np.argmax(far))
        log.flag(
            rs[j].source,
            "sun_azimuth",
            f"{int(far.sum())} of {n} timed records have a stored sun more than {MAX_SUN_GAP_DEG:g} deg from the "
            f"sun at their time (e.g. {gap[j]:.3g} deg here): {_whole_hours_off(gap, gaps)} "
            "All kept; check the data's time convention",
        )
        return goods
    drop: set[tuple[int, int]] = set()
    for j in np.nonzero(~(gap <= SUN_FLAG_DEG))[0]:
        r = rs[j]
        d_az = abs((az[j] - az_c[j] + 180.0) % 360.0 - 180.0) * math.cos(math.radians(el_c[j]))
        field = "sun_elevation" if abs(el[j] - el_c[j]) > d_az else "sun_azimuth"
        if gap[j] <= MAX_SUN_GAP_DEG:
            log.flag(
                r.source,
                field,
                f"the stored sun (azimuth {az[j]:.6g}, elevation {el[j]:.6g} deg) is {gap[j]:.3g} deg from the sun at "
                f"the record's time {r.datetime} (azimuth {az_c[j]:.6g}, elevation {el_c[j]:.6g} deg; more than "
                f"{SUN_FLAG_DEG:g} deg: rounded, or a time off by minutes?): record kept, check its sun and time",
            )
            continue
        log.skip_record(
            DataError(
                r.source,
                field,
                f"the stored sun (azimuth {az[j]:.6g}, elevation {el[j]:.6g} deg) is {gap[j]:.3g} deg from the sun "
                f"at the record's time {r.datetime} seen from heliostat {r.heliostat_id!r} (azimuth {az_c[j]:.4g}, "
                f"elevation {el_c[j]:.4g} deg; more than {MAX_SUN_GAP_DEG:g} deg: a sun in radians, or another time?)",
            )
        )
        drop.add(where[j])
    return [[r for k, r in enumerate(rs_i) if (i, k) not in drop] for i, rs_i in enumerate(goods)]


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
    bad_props: set[str] = set()  # heliostats counted as skipped already
    far = 0  # heliostats skipped for their distance from the reference point
    for p in sorted(properties, key=lambda p: p.heliostat_id):
        try:
            if validate:
                p = validate_properties(p)
            _check_actuator_law(p)
            distance = _distance_m(p.position_lla, origin_lla)  # pyright: ignore[reportArgumentType]
            rise = p.position_lla[2] - origin_lla[2]
            far += distance > MAX_HELIOSTAT_DISTANCE_M or abs(rise) > MAX_HELIOSTAT_HEIGHT_M
            if distance > MAX_HELIOSTAT_DISTANCE_M:
                raise DataError(
                    p.source,
                    "heliostat_position",
                    f"{distance / 1000:.4g} km from the plant's reference point "
                    f"(more than {MAX_HELIOSTAT_DISTANCE_M / 1000:g} km: not a heliostat of this plant)",
                )
            if abs(rise) > MAX_HELIOSTAT_HEIGHT_M:
                raise DataError(
                    p.source,
                    "heliostat_position",
                    f"altitude {p.position_lla[2]!r} m is {rise:+.4g} m from the plant's reference point "
                    f"(more than {MAX_HELIOSTAT_HEIGHT_M:g} m: not on the plant's ground)",
                )
            if p.heliostat_id in props_by_id:
                raise DataError(
                    p.source,
                    None,
                    f"second properties entry for heliostat {p.heliostat_id!r} "
                    f"(first: {props_by_id[p.heliostat_id].source})",
                )
        except DataError as e:
            log.skip(e, heliostats=int(p.heliostat_id not in bad_props))
            bad_props.add(p.heliostat_id)
            continue
        props_by_id[p.heliostat_id] = p
    by_h: dict[str, list[CalibrationRecord]] = collections.defaultdict(list)
    for r in records:
        if not isinstance(r.heliostat_id, str) or not r.heliostat_id:
            log.skip_record(
                DataError(
                    getattr(r, "source", None), "heliostat_id", f"must be a non-empty string, got {r.heliostat_id!r}"
                )
            )
            continue
        by_h[r.heliostat_id].append(r)

    at: dict[tuple, list[str]] = collections.defaultdict(list)
    for hid, p in props_by_id.items():
        at[tuple(p.position_lla)].append(hid)
    for same in (hids for hids in at.values() if len(hids) > 1):
        # A properties file copied in: which heliostat it describes is unknown, unless one
        # alone has records (the others' were refused, e.g. claimed by the timestamps file
        # for another heliostat: a copied folder) - then the others are the copies.
        with_records = [hid for hid in same if by_h.get(hid)]
        keep = with_records[0] if len(with_records) == 1 else None
        for hid in same:
            if hid == keep:
                continue
            others = ", ".join(repr(o) for o in same if o != hid)
            why = (
                f"the same position as heliostat {others}, which has the records: a copy of its folder"
                if keep is not None
                else f"the same position as heliostat {others}: one properties file copied to the other's place"
            )
            log.skip(DataError(props_by_id.pop(hid).source, "heliostat_position", why), heliostats=1)
            bad_props.add(hid)
    for hid in sorted(set(by_h) - set(props_by_id), key=str):
        rs = by_h[hid]
        log.skip(
            DataError(
                _common_dir([r.source for r in rs]),
                "heliostat_id",
                f"{len(rs)} calibration record(s) of heliostat {hid!r} skipped: "
                + ("bad properties file" if hid in bad_props else "no properties file"),
            ),
            records=len(rs),
            heliostats=int(hid not in bad_props),
        )

    ids = tuple(sorted(props_by_id))
    if not ids and far and far == len({p.heliostat_id for p in properties}):
        raise DataError(
            tower.source if origin is None else None,
            "power_plant_properties.coordinates" if origin is None else "origin",
            f"every heliostat ({far}) is more than {MAX_HELIOSTAT_DISTANCE_M / 1000:g} km from, or "
            f"{MAX_HELIOSTAT_HEIGHT_M:g} m above or below, the plant's reference point {list(origin_lla)}",
        )
    if not ids:
        rep = log.report()
        raise DataError(log.source, None, "no heliostat could be loaded\n" + rep.format())
    owners: dict[tuple, set[str]] = collections.defaultdict(set)  # measurement -> heliostats holding it
    for hid in ids:
        for r in by_h.get(hid, []):
            try:
                owners[_measurement(r)].add(hid)
            except TypeError:  # an unvalidated record with unhashable parts: checked later
                continue
    goods: list[list[CalibrationRecord]] = []
    for hid in ids:
        props = props_by_id[hid]
        good: list[CalibrationRecord] = []
        seen: set[int] = set()
        first = _first_of_each_measurement(by_h.get(hid, []))
        for r in by_h.get(hid, []):
            try:
                if validate:
                    r = validate_record(r)
                check_record_context(r, tower, props)
                if centroid == "helios" and r.focal_spot_helios is None:
                    raise DataError(r.source, "focal_spot.HeliOS", "missing (centroid='helios' uses HeliOS only)")
                if r.record_id in seen:
                    raise DataError(r.source, "record_id", f"duplicate record id {r.record_id} of {hid!r}")
                try:
                    same = first.get(_measurement(r), r.record_id)
                except TypeError:  # an unvalidated record with unhashable parts: not compared
                    same = r.record_id
                try:
                    copied_from = sorted(owners.get(_measurement(r), set()) - {hid})
                except TypeError:
                    copied_from = []
                if copied_from:
                    raise DataError(
                        r.source,
                        "record_id",
                        f"the same measurement as a record of heliostat {few_names(copied_from)} (identical time, "
                        "counts, sun and spots): which heliostat it belongs to is unknown, skipped in both",
                    )
                if same != r.record_id:
                    raise DataError(
                        r.source,
                        "record_id",
                        f"the same measurement as record {same} of {hid!r} (identical time, counts, sun and "
                        "spots): a copy, counted once",
                    )
            except DataError as e:
                log.skip_record(e)
                continue
            seen.add(r.record_id)
            good.append(r)
            off_target = spot_off_target(r, tower)
            if off_target is not None:
                log.flag(r.source, *off_target)
        goods.append(good)
    goods = _drop_sun_mismatches(goods, [props_by_id[hid].position_lla for hid in ids], log)
    per_h: list[list[CalibrationRecord]] = []
    per_t: list[list[float]] = []
    n_fallback = 0
    for hid, good in zip(ids, goods):
        props = props_by_id[hid]
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
            elif not EARLIEST_RECORD_TIME <= t <= time.time() + 86400.0:
                when = dt.datetime.fromtimestamp(t, dt.UTC).isoformat() if -6e10 < t < 2.5e11 else repr(t)
                log.flag(r.source, "datetime", f"{when} is before 2000 or in the future: record kept, check its time")
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
        enu, sun = _enu_sun_kernel(
            _bucket_rows(flat),
            np.asarray(origin_lla, np.float64),
            _bucket_rows(az.reshape(-1)),
            _bucket_rows(el.reshape(-1)),
        )
        enu = np.array(enu)[: len(flat)]
        sun = np.asarray(sun)
    sun = sun[: h * m].reshape(h, m, 3)
    pos_enu = enu[:h]
    spot_enu = enu[h : h + h * m].reshape(h, m, 3)
    corners_enu = enu[h + h * m :].reshape(n_t, 4, 3)
    for k, name in enumerate(planar):
        check_target_corners(tower.source, f"{name}.coordinates", *corners_enu[k], normal=tower.targets[name].normal)
    centres = corners_enu.mean(axis=1)
    for i in np.nonzero(n_valid == 0)[0]:
        spot_enu[i] = centres[0]

    acts = {
        k: np.array([[float(props_by_id[hid].actuators[i][k]) for i in range(2)] for hid in ids])
        for k in (
            "increment",
            "initial_stroke_length",
            "offset",
            "pivot_radius",
            "initial_angle",
            "min_increment",
            "max_increment",
            "clockwise_axis_movement",
        )
    }
    actuators = LinearActuators(
        increment=jax.device_put(_bucket_rows(acts["increment"])),
        initial_stroke_length=jax.device_put(_bucket_rows(acts["initial_stroke_length"])),
        offset=jax.device_put(_bucket_rows(acts["offset"])),
        pivot_radius=jax.device_put(_bucket_rows(acts["pivot_radius"])),
        initial_angle=jax.device_put(_bucket_rows(acts["initial_angle"])),
        sign=jax.device_put(_bucket_rows(np.where(acts["clockwise_axis_movement"] == 0, 1.0, -1.0))),
        min_counts=jax.device_put(_bucket_rows(acts["min_increment"])),
        max_counts=jax.device_put(_bucket_rows(acts["max_increment"])),
    )
    with jax.enable_x64(True):
        geometry, targets = _geometry_targets_kernel(
            _bucket_rows(pos_enu),
            actuators,
            _bucket_rows(np.array([props_by_id[k].joint_translation_1 for k in ids])),
            _bucket_rows(np.array([props_by_id[k].joint_translation_2 for k in ids])),
            _bucket_rows(np.array([props_by_id[k].concentrator_translation for k in ids])),
            _bucket_rows(
                np.array([[props_by_id[k].actuators[i]["type_axis"] == "ideal" for i in range(2)] for k in ids])
            ),
            tuple(corners_enu[:, c] for c in range(4)),
        )
    geometry = jax.tree.map(
        lambda x: jax.device_put(np.asarray(x)[:h]) if x.dtype == bool else _f(np.asarray(x)[:h]), geometry
    )
    targets = jax.tree.map(lambda x: _f(np.asarray(x)), targets)
    context = RecordContext(
        sun=_f(sun),
        unix_time=_f(utime),
        temperature=_f(weather[..., 0]),
        wind_speed=_f(weather[..., 1]),
        wind_direction=_f(np.deg2rad(weather[..., 2])),
        approach=_f(approach),
        target=jax.device_put(tidx),
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


def _listing(folder: Path, suffix: str, log: _Log) -> list[Path]:
    """The files in ``folder`` whose names end in ``suffix`` (not hidden), sorted; none
    for a missing folder; an unreadable one, or a file in its place, is named in the load
    report (a file ``<H>/Calibration`` was reported only as a heliostat without a valid
    record)."""
    try:
        with os.scandir(folder) as entries:
            return sorted(Path(e.path) for e in entries if e.name.endswith(suffix) and not e.name.startswith("."))
    except FileNotFoundError:
        return []
    except NotADirectoryError:
        log.skip(DataError(folder, None, f"not a folder (a file): no *{suffix} read from it"))
        return []
    except OSError as e:
        log.skip(DataError(folder, None, f"cannot list folder: {e.strerror or e}"))
        return []


def _note_skipped_targets(tower: TowerFile, log: _Log) -> None:
    """The tower file's targets :func:`read_tower` skipped by name (it warned of each): a
    note of the report, or with ``strict`` the first one's DataError; the records that
    name one are skipped as of an unknown target, saying why."""
    for name, problem in tower.skipped.items():
        if log.strict:
            raise DataError(tower.source, shown_value(name), f"not a target name ({problem})")
        log.notes.append(f"{tower.source}: target {shown_value(name)} skipped: not a target name ({problem})")


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
        heliostats: ids to load (a list, or one id as a string; default: all); others
            are not read.
        strict: raise the first :class:`DataError` instead of skipping.
        origin: WGS84 ENU origin overriding the tower file's plant coordinates.

    Raises:
        TypeError: ``path`` is not a path (a number, a list); ``heliostats`` is not an
            id or a list of ids.
        ValueError: ``path`` is empty (not the working directory).
        DataError: a missing/invalid tower file or no loadable heliostat (always);
            any bad input when ``strict``.
    """
    if path is not None and not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a directory path (str or os.PathLike) or None, got {type(path).__name__}")
    if path is not None:
        check_path_argument(path)  # "" is the working directory (Path("") is "."), loaded without a word
    _check_centroid(centroid)
    root = default_data_dir() if path is None else Path(path)
    if not root.is_dir():
        raise DataError(root, None, "not a directory")
    if not os.access(root, os.R_OK | os.X_OK):  # else its listing is empty: "found 0" tower files
        raise DataError(root, None, "cannot read folder: permission denied")
    log = _Log(str(root), strict, centroid)
    towers = sorted(root.glob("*" + TOWER_FILE_SUFFIX))
    if len(towers) != 1:
        raise DataError(root, None, f"expected one *{TOWER_FILE_SUFFIX}, found {len(towers)}")
    log.files_seen += 1
    tower = read_tower(towers[0])
    _note_skipped_targets(tower, log)

    timestamps: Mapping = {}
    ts_path = root / TIMESTAMPS_FILE
    if ts_path.is_file() or ts_path.is_symlink():  # a dangling or looping link is named, not taken for no file
        log.files_seen += 1
        try:
            timestamps = read_timestamps(ts_path, on_error=log.skip_entry)
        except DataError as e:
            log.skip(e)
    else:
        if ts_path.exists():
            log.skip(DataError(ts_path, None, "not a file"))
    timestamps = _with_metadata_times(root, timestamps, log)
    if not timestamps:
        log.notes.append(f"no {TIMESTAMPS_FILE} and no {METADATA_GLOB}: every record's time is unknown")

    weather: dict[tuple[str, int], dict[str, float]] = {}
    weather_rows: dict[tuple[str, int], CalibrationRecord] = {}
    csv_path = root / WEATHER_CSV_FILE
    if csv_path.is_file() or csv_path.is_symlink():
        log.files_seen += 1
        try:
            rows = read_weather_csv(csv_path, on_error=log.skip_entry)
        except DataError as e:
            log.skip(e)
            rows = ()
        weather = {(r.heliostat_id, r.record_id): r.weather for r in rows}
        weather_rows = {(r.heliostat_id, r.record_id): r for r in rows}
        _flag_repeated_weather(rows, str(csv_path), log)
        _flag_weather_gaps(rows, str(csv_path), log)
    elif csv_path.exists():
        log.skip(DataError(csv_path, None, "not a file: no weather"))

    dirs = []
    for d in sorted(root.iterdir()):
        if not d.is_dir():
            continue
        if not os.access(d, os.R_OK | os.X_OK):  # is_dir() of its subfolders would say False: name it
            log.skip(DataError(d, None, "cannot read folder: permission denied"), heliostats=1)
        elif (d / "Properties").is_dir() or (d / "Calibration").is_dir():
            if problem := heliostat_id_problem(d.name):
                log.skip(DataError(d, None, f"folder name {problem}: not a heliostat id"), heliostats=1)
            else:
                dirs.append(d)
    if not dirs and (any(root.glob("*" + CALIBRATION_SUFFIX)) or any(root.glob("*" + PROPERTIES_SUFFIX))):
        raise DataError(
            root,
            None,
            "holds PAINT files in one folder (the layout of PAINT's download for a dataset, which "
            "cannot tell a record's heliostat); heliojax reads the per-heliostat layout that PAINT's "
            f"STAC client writes by default: <H>/Properties/<H>{PROPERTIES_SUFFIX}, "
            f"<H>/Calibration/<ID>{CALIBRATION_SUFFIX}",
        )
    if heliostats is not None:
        wanted = set(requested_heliostats(heliostats, "load_paint_directory"))
        if wanted and not wanted & {d.name for d in dirs}:  # another fleet's folder: one line, not a report
            raise DataError(
                root,
                None,
                f"holds none of the requested heliostats ({few_names(sorted(wanted))}); "
                f"its heliostats: {few_names([d.name for d in dirs]) or 'none'}",
            )
        for hid in sorted(wanted - {d.name for d in dirs}):
            log.skip(DataError(root / hid, None, f"heliostat {hid!r} requested but not in the directory"), heliostats=1)
        dirs = [d for d in dirs if d.name in wanted]

    properties: list[HeliostatProperties] = []
    records: list[CalibrationRecord] = []
    for d in dirs:
        hid = d.name
        prop_files = _listing(d / "Properties", PROPERTIES_SUFFIX, log)
        cal_files = _listing(d / "Calibration", CALIBRATION_SUFFIX, log)
        log.files_seen += len(prop_files) + len(cal_files)
        expected = heliostat_properties_path(root, hid)
        try:
            if not prop_files:
                if not cal_files:
                    continue
                raise DataError(
                    expected,
                    None,
                    f"missing: {len(cal_files)} calibration record(s) of heliostat {hid!r} have no properties file",
                )
            if len(prop_files) > 1 or prop_files[0].name != expected.name:
                raise DataError(
                    d / "Properties", None, f"expected exactly {expected.name}, found {[p.name for p in prop_files]}"
                )
            props = read_heliostat_properties(prop_files[0], heliostat_id=hid)
            for field, reason in props.notes:
                log.flag(props.source, field, reason)
        except DataError as e:
            log.skip(e, records=len(cal_files), heliostats=1)
            if prop_files and cal_files:
                log.skipped.append(
                    ReportEntry(
                        str(d / "Calibration"),
                        None,
                        f"{len(cal_files)} calibration record(s) skipped with heliostat {hid!r} (bad properties file)",
                    )
                )
            continue
        properties.append(props)
        for cf in cal_files:
            try:
                records.append(
                    read_calibration_record(
                        cf, heliostat_id=hid, timestamps=timestamps, weather=weather, tower=tower, properties=props
                    )
                )
            except DataError as e:
                log.skip_record(e)
    for r in records:
        for field, reason in r.notes:
            log.flag(r.source, field, reason)
    _flag_records_before_renovation(properties, records, log)
    records = [_weather_of_its_time(r, weather_rows.get((r.heliostat_id, r.record_id)), log) for r in records]
    owner = {r.record_id: r.heliostat_id for r in records}
    for hid, rid in weather:  # joined by (heliostat, record): a row naming the wrong heliostat joins nothing
        if rid in owner and owner[rid] != hid:
            log.flag(
                str(csv_path),
                f"record {rid}",
                f"weather row for heliostat {hid!r}, but record {rid} is {owner[rid]!r}'s: its weather is not used",
            )
    return _assemble(tower, properties, records, centroid=centroid, origin=origin, log=log, validate=False)


def _with_metadata_times(
    root: Path, timestamps: Mapping[int, TimestampEntry], log: _Log
) -> Mapping[int, TimestampEntry]:
    """``timestamps`` completed from PAINT's calibration metadata CSV(s) (:data:`METADATA_GLOB`,
    written by PAINT's own STAC client, which writes no ``calibration-timestamps.json``):
    a record without an entry takes the CSV's; where both name a record and disagree
    (heliostat, or time by more than a second), the timestamps file's entry is kept and
    the disagreement flagged."""
    files = sorted(root.glob(METADATA_GLOB))
    if not files:
        return timestamps
    merged = dict(timestamps)
    added = 0
    for path in files:
        log.files_seen += 1
        try:
            entries = read_metadata_times(path, on_error=log.skip_entry)
        except DataError as e:
            log.skip(e)
            continue
        for rid, entry in entries.items():
            kept = merged.get(rid)
            if kept is None:
                merged[rid] = entry
                added += 1
            elif (
                kept.heliostat_id != entry.heliostat_id
                or abs(datetime_to_unix(kept.datetime) - datetime_to_unix(entry.datetime)) > 1.0
            ):
                log.flag(
                    str(path),
                    f"record {rid}",
                    f"{entry.heliostat_id} at {entry.datetime}, but {TIMESTAMPS_FILE} says "
                    f"{kept.heliostat_id} at {kept.datetime}: the latter is used",
                )
    if added:
        log.notes.append(f"{added} record time(s) from {', '.join(str(f.relative_to(root)) for f in files)}")
    return merged


def _flag_records_before_renovation(
    properties: Sequence[HeliostatProperties], records: Sequence[CalibrationRecord], log: _Log
) -> None:
    """Flags a heliostat whose records begin before its ``renovation`` (PAINT: the date or
    date range of the mechanical retrofit): the kinematics may have changed in between,
    which one fitted model does not describe (the change-point scan looks for the jump).
    Every shared download's heliostat has its records after its renovation."""
    times: dict[str, list[float]] = collections.defaultdict(list)
    for r in records:
        if r.datetime:
            times[r.heliostat_id].append(datetime_to_unix(r.datetime))
    for p in properties:
        if p.renovation is None:
            continue
        try:
            end = datetime_to_unix(p.renovation.split("/")[-1].strip()) + 86400.0  # the end day included
        except (ValueError, TypeError, OverflowError):
            log.flag(p.source, "renovation", f"{p.renovation[:60]!r} is not a date or date range: not checked")
            continue
        before = sum(t < end for t in times[p.heliostat_id])
        if before:
            log.flag(
                p.source,
                "renovation",
                f"{before} of {len(times[p.heliostat_id])} timed record(s) were measured before the retrofit of "
                f"{p.renovation}: "
                "the kinematics may differ across it (a change point; heliojax calibrate looks for one)",
            )


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
        heliostats: ids to load (a list, or one id as a string; default: all in the CSV).
        strict: raise the first :class:`DataError` instead of skipping.
        origin: WGS84 ENU origin overriding the tower file's.
    """
    _check_centroid(centroid)
    log = _Log(str(csv_path), strict, centroid)
    tower = read_tower(tower_path)
    _note_skipped_targets(tower, log)
    log.files_seen += 2
    rows = read_weather_csv(csv_path, on_error=log.skip_record)
    if heliostats is not None:
        wanted = set(requested_heliostats(heliostats, "load_weather_csv_fleet"))
        for hid in sorted(wanted - {r.heliostat_id for r in rows}):
            log.skip(
                DataError(csv_path, "heliostat_id", f"heliostat {hid!r} requested but not in the CSV"), heliostats=1
            )
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
            log.skipped.append(
                ReportEntry(
                    str(csv_path),
                    "heliostat_id",
                    f"{len(bad)} row(s) of heliostat {hid!r} skipped (bad properties file)",
                )
            )
            log.records_skipped += len(bad)
            rows = tuple(r for r in rows if r.heliostat_id != hid)
    return _assemble(tower, properties, rows, centroid=centroid, origin=origin, log=log, validate=False)
