"""Calibration records (``<H>/Calibration/<ID>-calibration-properties.json``)."""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, no_type_check

from .._errors import DataError
from .._io import check_path_argument, heliostat_id_problem, shown_value
from ._common import (
    CALIBRATION_SUFFIX,
    CORNERS,
    MAX_SPOT_DISTANCE_M,
    PROPERTIES_SUFFIX,
    RECORD_ID_LIMIT,
    TIMESTAMPS_FILE,
    WEATHER_KEYS,
    CalibrationRecord,
    HeliostatProperties,
    TimestampEntry,
    TowerFile,
    Vec3,
    _check,
    _check_datetime,
    _check_weather_value,
    _distance_m,
    _join,
    _latlon_ok,
    _load_json,
    _local_offset_m,
    _nan_weather,
    _Node,
    _record_id_from_name,
    _roundtrip,
    _type_name,
    _write_json,
)
from ._tower import skipped_target_message

# ======================================================================================
# Calibration records
# ======================================================================================


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _record_from_json(
    file: str,
    data: Any,
    record_id: int,
    heliostat_id: str,
    datetime: str | None,
    weather: Mapping[str, float] | None,
) -> CalibrationRecord:
    root = _Node(file, data)
    motor = root.node("motor_position")
    c1 = motor.integer("axis_1_motor_position")
    c2 = motor.integer("axis_2_motor_position")
    target = root.string("target_name")
    el = float(root.number("sun_elevation"))
    az = float(root.number("sun_azimuth"))
    _check(-90.0 <= el <= 90.0, file, "sun_elevation", f"{el!r} outside [-90, 90] deg")
    _check(el > 0.0, file, "sun_elevation", f"{el!r} deg: the sun is below the horizon (no reflection to measure)")
    _check(-360.0 <= az <= 360.0, file, "sun_azimuth", f"{az!r} outside [-360, 360] deg")
    fs = root.node("focal_spot")
    spots: dict[str, Vec3 | None] = {}
    notes: list[tuple[str, str]] = []
    not_finite = False
    for key in ("HeliOS", "UTIS"):
        spots[key] = None
        if not fs.has(key) or fs.get(key) is None:
            continue
        value = fs.get(key)
        if isinstance(value, list) and any(isinstance(x, float) and math.isnan(x) for x in value):
            # PAINT writes a centroid it could not compute as NaN (json.dump of a NaN
            # value): the same as a missing one, the other centroid is used
            notes.append((fs.field(key), "not finite (NaN): read as missing, the other centroid is used"))
            not_finite = True
            continue
        spots[key] = fs.vec3(key)
        _latlon_ok(file, fs.field(key), spots[key])  # type: ignore[arg-type]
    if spots["HeliOS"] is None and spots["UTIS"] is None:
        if not_finite:
            raise DataError(file, "focal_spot", "no usable centroid (HeliOS and UTIS missing or not finite)")
        raise DataError(file, "focal_spot", "neither a HeliOS nor a UTIS centroid")
    w = _nan_weather()
    if weather is not None:
        w.update({k: (math.nan if math.isnan(v) else v) for k, v in weather.items() if k in w})
    return CalibrationRecord(
        record_id=record_id,
        heliostat_id=heliostat_id,
        axis_1_counts=c1,
        axis_2_counts=c2,
        target_name=target,
        sun_azimuth_deg=az,
        sun_elevation_deg=el,
        focal_spot_helios=spots["HeliOS"],
        focal_spot_utis=spots["UTIS"],
        datetime=datetime,
        weather=w,
        source=file,
        notes=tuple(notes),
    )


def _record_to_json(r: CalibrationRecord) -> dict:
    fs: dict[str, Any] = {}
    if r.focal_spot_helios is not None:
        fs["HeliOS"] = list(r.focal_spot_helios)
    if r.focal_spot_utis is not None:
        fs["UTIS"] = list(r.focal_spot_utis)
    return {
        "motor_position": {"axis_1_motor_position": r.axis_1_counts, "axis_2_motor_position": r.axis_2_counts},
        "target_name": r.target_name,
        "sun_elevation": r.sun_elevation_deg,
        "sun_azimuth": r.sun_azimuth_deg,
        "focal_spot": fs,
    }


PLACEHOLDER_SPOT_M = 1e-6
"""A focal spot this close to its target's centre (the tower file's ``center`` or its
corners' mean) is that point copied in, not a measurement (a camera's spot centroid
has centimetres of noise): a failed centroid's placeholder."""


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def spot_off_target(record: CalibrationRecord, tower: TowerFile) -> tuple[str, str] | None:
    """``(field, reason)`` for a focal spot of ``record`` farther from its (planar) target's
    centre than the target's farthest corner: no spot on the target (a camera sees only
    the target; real PAINT spots lie within 0.6 of that distance), or None."""
    t = tower.targets.get(record.target_name)
    if t is None or not t.is_planar_target:
        return None
    centre: Vec3 = tuple(sum(t.points[c][k] for c in CORNERS) / len(CORNERS) for k in range(3))  # pyright: ignore[reportAssignmentType]
    reach = max(_distance_m(t.points[c], centre) for c in CORNERS)
    for field, spot in (("focal_spot.UTIS", record.focal_spot_utis), ("focal_spot.HeliOS", record.focal_spot_helios)):
        distance = 0.0 if spot is None else _distance_m(spot, centre)
        if distance > reach:
            return field, (
                f"{distance:.4g} m from the centre of target {record.target_name!r}, beyond its corners "
                f"({reach:.3g} m): not a spot on it; record kept, check its spot and target"
            )
    return None


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def check_record_context(
    record: CalibrationRecord,
    tower: TowerFile | None = None,
    properties: HeliostatProperties | Mapping[str, HeliostatProperties] | None = None,
) -> None:
    """Checks of a record against its tower file and heliostat properties.

    Raises:
        DataError: (file = ``record.source``) for a ``target_name`` that is not a
            planar target of ``tower``; for a focal spot more than
            :data:`MAX_SPOT_DISTANCE_M` from its target's centre; for a heliostat missing from ``properties``
            (when a mapping id -> properties is given); for motor counts outside
            ``[min_increment, max_increment]``.
    """
    file = record.source
    if tower is not None:
        t = tower.targets.get(record.target_name)
        if t is None:
            skipped = skipped_target_message(tower, record.target_name)  # a name the tower file's reader refused
            raise DataError(
                file,
                "target_name",
                f"unknown target {shown_value(record.target_name)}: {skipped}"
                if skipped
                else f"unknown target {record.target_name!r} (tower file has {', '.join(tower.planar_target_names)})",
            )
        if not t.is_planar_target:
            raise DataError(file, "target_name", f"{record.target_name!r} is not a planar calibration target")
        centre: Vec3 = tuple(sum(t.points[c][k] for c in CORNERS) / len(CORNERS) for k in range(3))  # pyright: ignore[reportAssignmentType]
        for field, spot in (
            ("focal_spot.UTIS", record.focal_spot_utis),
            ("focal_spot.HeliOS", record.focal_spot_helios),
        ):
            distance = 0.0 if spot is None else _distance_m(spot, centre)
            if distance > MAX_SPOT_DISTANCE_M:
                raise DataError(
                    file,
                    field,
                    f"{distance:.4g} m from the centre of target {record.target_name!r} "
                    f"(more than {MAX_SPOT_DISTANCE_M:g} m: not a spot on it)",
                )
            listed = [centre, *([t.points["center"]] if "center" in t.points else [])]
            if spot is not None and min(_distance_m(spot, c) for c in listed) < PLACEHOLDER_SPOT_M:
                raise DataError(
                    file,
                    field,
                    f"exactly the centre of target {record.target_name!r} (within {PLACEHOLDER_SPOT_M:g} m): "
                    "a placeholder of a centroid that failed, not a measured spot",
                )
    if properties is None:
        return
    if isinstance(properties, Mapping):
        props = properties.get(record.heliostat_id)
        if props is None:
            raise DataError(file, "heliostat_id", f"heliostat {record.heliostat_id!r} has no properties file")
    else:
        props = properties
        if props.heliostat_id != record.heliostat_id:
            raise DataError(
                file,
                "heliostat_id",
                f"record of {record.heliostat_id!r} checked against properties of {props.heliostat_id!r}",
            )
    for axis, count in ((1, record.axis_1_counts), (2, record.axis_2_counts)):
        a = props.actuators[axis - 1]
        lo, hi = a["min_increment"], a["max_increment"]
        if not lo <= count <= hi:
            raise DataError(
                file,
                f"motor_position.axis_{axis}_motor_position",
                f"count {_shown_count(count)} outside [min_increment, max_increment] = "
                f"[{_shown_count(lo)}, {_shown_count(hi)}] of {Path(props.source).name}",
            )
    target = None if tower is None else tower.targets.get(record.target_name)
    if target is not None and target.normal is not None and any(target.normal):
        middle = tuple(sum(target.points[c][k] for c in CORNERS) / len(CORNERS) for k in range(3))
        front = _front_distance_m(props.position_lla, middle, target.normal)  # pyright: ignore[reportArgumentType]
        if not front > 0.0:
            raise DataError(
                file,
                "target_name",
                f"heliostat {record.heliostat_id!r} ({Path(props.source).name}: heliostat_position) stands "
                f"{-front:.3g} m behind the plane of target {record.target_name!r}, whose front faces "
                f"{list(target.normal)}: no reflection reaches that face (a wrong position or target?)",
            )


def _shown_count(count: Any) -> str:
    """A motor count as a message shows it: every digit up to 15 of them, else in
    ``%g`` form (a count of 1e300 was printed with its 301 digits)."""
    try:
        return str(count) if abs(count) < 10**15 else f"{float(count):.6g}"
    except (OverflowError, TypeError, ValueError):
        return shown_value(count)


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _front_distance_m(point: Vec3, centre: Vec3, normal: Vec3) -> float:
    """Signed distance (m) of the WGS84 ``point`` from the plane through the WGS84
    ``centre`` with the ENU ``normal`` (positive on the side it faces;
    :func:`_local_offset_m`)."""
    offset = _local_offset_m(point, centre)
    return sum(x * n for x, n in zip(offset, normal, strict=True)) / math.hypot(*normal)


def validate_record(record: CalibrationRecord) -> CalibrationRecord:
    """Run the reader's value checks on an in-memory :class:`CalibrationRecord`
    (serialise and re-parse, plus the date-time and weather); returns the
    re-parsed (equal) record.

    Raises:
        DataError: with ``record.source`` as the file.
    """
    file = record.source
    rid = record.record_id
    if isinstance(rid, bool) or not isinstance(rid, numbers.Integral) or not 0 <= rid < RECORD_ID_LIMIT:
        raise DataError(file, "record_id", f"expected an integer in [0, 2**31), got {rid!r}")
    if not isinstance(record.heliostat_id, str) or not record.heliostat_id:
        raise DataError(file, "heliostat_id", "expected a non-empty string")
    if record.datetime is not None:
        _check_datetime(file, "datetime", record.datetime)
    weather = _check_weather(file, "weather", record.weather)
    try:
        data = _roundtrip(_record_to_json(record))
    except (TypeError, ValueError) as e:
        raise DataError(file, None, f"not serialisable: {e}") from None
    return _record_from_json(file, data, int(rid), record.heliostat_id, record.datetime, weather)


def _check_weather(file: str, field: str, weather: Any) -> dict[str, float]:
    if not isinstance(weather, Mapping):
        raise DataError(file, field, "expected a mapping")
    out = _nan_weather()
    for k, v in weather.items():
        if k not in out:
            raise DataError(file, _join(field, str(k)), f"unknown weather key (known: {', '.join(WEATHER_KEYS)})")
        if isinstance(v, bool) or not isinstance(v, numbers.Real):
            raise DataError(file, _join(field, k), f"expected a number, got {_type_name(v)}")
        v = float(v)
        if math.isinf(v):
            raise DataError(file, _join(field, k), f"not finite ({v!r}); use NaN for unknown")
        _check_weather_value(file, _join(field, k), k, v)
        out[k] = math.nan if math.isnan(v) else v
    return out


def calibration_record_path(root: str | os.PathLike, heliostat_id: str, record_id: int) -> Path:
    """``root/<H>/Calibration/<ID>-calibration-properties.json``.

    Raises:
        TypeError, ValueError: ``root`` is no path, ``heliostat_id`` no heliostat id (a
            ``../x`` led out of ``root``) or ``record_id`` no whole number >= 0 (``2.5``
            and ``-1`` named files that :func:`read_calibration_record` refuses).
    """
    _check_path_parts(root, heliostat_id)
    if isinstance(record_id, bool) or not isinstance(record_id, numbers.Integral) or record_id < 0:
        number = not isinstance(record_id, bool) and isinstance(record_id, numbers.Integral | float)
        kind = ValueError if number else TypeError
        raise kind(f"record_id: expected a whole number >= 0 (a PAINT record id), got {shown_value(record_id)}")
    return Path(root) / heliostat_id / "Calibration" / f"{int(record_id)}{CALIBRATION_SUFFIX}"


def heliostat_properties_path(root: str | os.PathLike, heliostat_id: str) -> Path:
    """``root/<H>/Properties/<H>-heliostat-properties.json``.

    Raises:
        TypeError, ValueError: ``root`` is no path or ``heliostat_id`` no heliostat id
            (:func:`heliojax._io.heliostat_id_problem`: ``../x`` led out of ``root``).
    """
    _check_path_parts(root, heliostat_id)
    return Path(root) / heliostat_id / "Properties" / f"{heliostat_id}{PROPERTIES_SUFFIX}"


def _check_path_parts(root: object, heliostat_id: object) -> None:
    """``root`` is a path and ``heliostat_id`` a heliostat id (a folder's name in it)."""
    check_path_argument(root, "root")
    if not isinstance(heliostat_id, str):
        raise TypeError(f"heliostat_id: expected a heliostat id (a string), got {type(heliostat_id).__name__}")
    problem = heliostat_id_problem(heliostat_id)
    if problem is not None:
        raise ValueError(f"heliostat_id: {shown_value(heliostat_id)} is not a heliostat id ({problem})")


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def read_calibration_record(
    path: str | os.PathLike,
    *,
    heliostat_id: str | None = None,
    timestamps: Mapping[int, TimestampEntry] | None = None,
    weather: Mapping[tuple[str, int], Mapping[str, float]] | None = None,
    tower: TowerFile | None = None,
    properties: HeliostatProperties | Mapping[str, HeliostatProperties] | None = None,
) -> CalibrationRecord:
    """Read and validate a ``<ID>-calibration-properties.json``.

    Args:
        path: the file; the record id is the ``<ID>`` of its name.
        heliostat_id: the heliostat; default: the directory ``<H>`` of
            ``<H>/Calibration/<file>``.
        timestamps: :func:`read_timestamps` of the download; gives ``datetime``
            (None when the record has no entry). An entry naming another heliostat
            is an error.
        weather: ``(heliostat_id, record_id) -> weather`` (see :func:`read_weather_csv`).
        tower: when given, ``target_name`` must be one of its planar targets.
        properties: the heliostat's properties, or a mapping id -> properties; when
            given, the counts must lie in ``[min_increment, max_increment]`` and (for a
            mapping) the heliostat must have properties.

    Raises:
        TypeError, ValueError: ``path`` is no path or empty
            (:func:`heliojax._io.check_path_argument`).
        DataError: naming the file and the dotted field.
    """
    check_path_argument(path)
    path = Path(path)
    file = str(path)
    rid = _record_id_from_name(path)
    if heliostat_id is None:
        if path.parent.name == "Calibration" and path.parent.parent.name:
            heliostat_id = path.parent.parent.name
        elif timestamps is not None and rid in timestamps:
            heliostat_id = timestamps[rid].heliostat_id
        else:
            raise DataError(file, None, "cannot tell the heliostat (not in '<H>/Calibration/'; pass heliostat_id)")
    dt = None
    if timestamps is not None and rid in timestamps:
        entry = timestamps[rid]
        if entry.heliostat_id != heliostat_id:
            raise DataError(
                file,
                "heliostat_id",
                f"{TIMESTAMPS_FILE} assigns record {rid} to {entry.heliostat_id!r}, "
                f"the file lies under {heliostat_id!r}",
            )
        dt = entry.datetime
    w = None if weather is None else weather.get((heliostat_id, rid))
    record = _record_from_json(file, _load_json(path), rid, heliostat_id, dt, w)
    check_record_context(record, tower, properties)
    return record


def write_calibration_record(path: str | os.PathLike, record: CalibrationRecord) -> None:
    """Write the JSON part of a record (counts, target, sun, centroids) atomically.
    The id lives in the file name, the time in ``calibration-timestamps.json``, the
    weather in ``calibration-with-weather.csv``."""
    _write_json(path, _record_to_json(record))
