"""PAINT files: raw, validated Python records and their writers.

This module is the data boundary of heliojax. It reads (and writes, atomically)
the files of a PAINT download directory::

    <PLANT>-tower-measurements.json                   tower, calibration targets, receiver
    <H>/Properties/<H>-heliostat-properties.json      one per heliostat
    <H>/Calibration/<ID>-calibration-properties.json  one per calibration record
    calibration-timestamps.json                       <ID> -> {heliostat_id, datetime (UTC)}
    calibration-with-weather.csv                      optional: one row per record, with weather

into frozen dataclasses of plain Python values (:class:`TowerFile`,
:class:`HeliostatProperties`, :class:`CalibrationRecord`). Units are those of
the files: WGS84 ``[lat_deg, lon_deg, alt_m]`` positions, degrees for the sun
(PAINT azimuth: 0 = south, positive toward east), metres and radians for the
actuators, motor positions in integer stepper counts. The conversion to the
ENU frame and to arrays happens in :mod:`heliojax._fleet`.

Validation
----------
Every reader validates what it reads and raises :class:`heliojax.DataError`
``(file, field, reason)`` with the file and the dotted field (for example
``motor_position.axis_1_motor_position`` or
``kinematics_properties.actuators[1].increment``) for: unreadable files,
malformed JSON (or bytes that are not UTF-8), a top level that is not an
object, missing fields, fields of the wrong type (numbers must be JSON numbers,
not strings or booleans), non-finite numbers (``NaN``, ``Infinity``, overflow),
non-integral motor counts, impossible values (non-positive lengths or
increments, ``min_increment >= max_increment``), and, when the caller passes
the context, an unknown or non-planar ``target_name``, motor counts outside
``[min_increment, max_increment]`` and records of a heliostat without a
properties file. No other exception escapes a reader for bad file *content*
(the property-based tests feed random JSON and junk bytes).

Readers of multi-entry files (:func:`read_timestamps`, :func:`read_weather_csv`)
take ``on_error``: ``None`` raises the first :class:`DataError`; a callable
receives each bad entry's :class:`DataError` and the entry is skipped.

Writers
-------
The writers go through :func:`heliojax._io.atomic_write`. Floats are written
with Python's ``repr`` (the shortest string that round-trips), integers as
integers, so a record written by :func:`write_paint_directory` reads back
bit-identical. NaN (unknown weather) is written as an empty CSV cell.

Facts about the real files (checked on the shared download)
-----------------------------------------------------------
* ``focal_spot`` holds ``HeliOS`` and ``UTIS`` centroids; ``UTIS`` may be absent
  or ``null``. The CSV's ``focal_spot_*`` columns equal the *HeliOS* centroid of
  the same record (all 326 records present in both forms), so a CSV row becomes a
  record with a HeliOS centroid only.
* Record ids are sequential in time: the 1,706 timestamped ids of the shared
  download are in strictly chronological order.
* The CSV's ``wind_direction`` is in degrees (0-360; the direction the wind comes
  from, clockwise from north), ``wind_speed`` m/s, ``temperature`` deg C, ``dni``
  W/m^2, ``humidity`` %, ``pressure`` hPa.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import numbers
import os
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ._errors import DataError
from ._io import atomic_write
from ._sun import datetime_to_unix

__all__ = [
    "ACTUATOR_KEYS",
    "CSV_COLUMNS",
    "TIMESTAMPS_FILE",
    "TOWER_FILE_SUFFIX",
    "WEATHER_CSV_FILE",
    "WEATHER_KEYS",
    "CalibrationRecord",
    "Facet",
    "HeliostatProperties",
    "TargetEntry",
    "TimestampEntry",
    "TowerFile",
    "calibration_record_path",
    "check_record_context",
    "heliostat_properties_path",
    "read_calibration_record",
    "read_heliostat_properties",
    "read_timestamps",
    "read_tower",
    "read_weather_csv",
    "validate_properties",
    "validate_record",
    "write_calibration_record",
    "write_heliostat_properties",
    "write_paint_directory",
    "write_timestamps",
    "write_tower",
    "write_weather_csv",
]

Vec3 = tuple[float, float, float]

TOWER_FILE_SUFFIX = "-tower-measurements.json"
"""File-name suffix of the tower file (``<PLANT>-tower-measurements.json``)."""
TIMESTAMPS_FILE = "calibration-timestamps.json"
WEATHER_CSV_FILE = "calibration-with-weather.csv"
PROPERTIES_SUFFIX = "-heliostat-properties.json"
CALIBRATION_SUFFIX = "-calibration-properties.json"

WEATHER_KEYS = ("temperature", "wind_speed", "wind_direction", "dni", "humidity", "pressure")
"""Weather of a record (file units: deg C, m/s, deg, W/m^2, %, hPa); NaN = unknown."""

CORNERS = ("upper_left", "upper_right", "lower_left", "lower_right")
"""Corner points that make a tower entry a usable planar target."""

ACTUATOR_REQUIRED = (
    "type_axis",
    "min_increment",
    "max_increment",
    "increment",
    "initial_stroke_length",
    "offset",
    "pivot_radius",
    "clockwise_axis_movement",
    "initial_angle",
)
ACTUATOR_OPTIONAL = (
    "offset_shift",
    "radius_shift",
    "min_movement_angle",
    "max_movement_angle",
    "movement_speed",
)
ACTUATOR_KEYS = (
    "type_axis",
    "min_increment",
    "max_increment",
    "increment",
    "offset_shift",
    "initial_stroke_length",
    "offset",
    "pivot_radius",
    "radius_shift",
    "clockwise_axis_movement",
    "initial_angle",
    "min_movement_angle",
    "max_movement_angle",
    "movement_speed",
)
"""Keys of an actuator entry, in PAINT's order. The first group
(:data:`ACTUATOR_REQUIRED`) is required; the rest are kept when present."""

CSV_COLUMNS = (
    "heliostat_id",
    "timestamp",
    "sample_id",
    "sun_elevation",
    "sun_azimuth",
    "axis_1_motor_position",
    "axis_2_motor_position",
    "target_name",
    "heliostat_lat",
    "heliostat_lon",
    "heliostat_alt",
    "focal_spot_lat",
    "focal_spot_lon",
    "focal_spot_alt",
    "target_center_lat",
    "target_center_lon",
    "target_center_alt",
    "tracking_error_lat",
    "tracking_error_lon",
    "tracking_error_alt",
    "wind_speed",
    "wind_direction",
    "dni",
    "temperature",
    "humidity",
    "pressure",
)
"""Columns of ``calibration-with-weather.csv`` (in the shared file's order)."""

_CSV_REQUIRED = (
    "heliostat_id",
    "timestamp",
    "sample_id",
    "sun_elevation",
    "sun_azimuth",
    "axis_1_motor_position",
    "axis_2_motor_position",
    "target_name",
    "focal_spot_lat",
    "focal_spot_lon",
    "focal_spot_alt",
)

_MEMORY = "<memory>"
_ID_RE = re.compile(r"^[0-9]+$")


def _nan_weather() -> dict[str, float]:
    return {k: math.nan for k in WEATHER_KEYS}


# ======================================================================================
# Records
# ======================================================================================


@dataclasses.dataclass(frozen=True)
class TargetEntry:
    """One entry of the tower file besides ``power_plant_properties``.

    Attributes:
        name: the entry's key (``"solar_tower_juelich_upper"``, ``"receiver"``, ...).
        type: ``"planar"``, ``"convex_cylinder"``, ...
        normal: ``normal_vector`` as written (ENU components), or None.
        points: every named point of ``coordinates`` (``center``, ``upper_left``, ...),
            WGS84 ``(lat_deg, lon_deg, alt_m)``, in file order.
        extra: other keys of the entry (``radius``, ``opening_angle``, ...), kept verbatim
            (JSON scalars).
    """

    name: str
    type: str
    normal: Vec3 | None
    points: dict[str, Vec3]
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def is_planar_target(self) -> bool:
        """True for a ``planar`` entry with the four corners: a calibration target."""
        return self.type == "planar" and all(c in self.points for c in CORNERS)


@dataclasses.dataclass(frozen=True)
class TowerFile:
    """The tower file: plant reference point and targets.

    Attributes:
        plant_id: ``power_plant_properties.ID``.
        origin_lla: ``power_plant_properties.coordinates``, the ENU origin (WGS84).
        targets: every other entry (receiver included), in file order.
        source: the file it came from.
    """

    plant_id: str
    origin_lla: Vec3
    targets: dict[str, TargetEntry]
    source: str = _MEMORY

    @property
    def planar_target_names(self) -> tuple[str, ...]:
        """Names of the entries usable as calibration targets, in file order."""
        return tuple(n for n, t in self.targets.items() if t.is_planar_target)


@dataclasses.dataclass(frozen=True)
class Facet:
    """One facet of ``facet_properties.facets`` (metres, heliostat surface frame)."""

    translation_vector: Vec3
    canting_e: Vec3
    canting_n: Vec3


@dataclasses.dataclass(frozen=True)
class HeliostatProperties:
    """A ``<H>-heliostat-properties.json``.

    Attributes:
        heliostat_id: from the file name (``<H>-heliostat-properties.json``).
        position_lla: ``heliostat_position`` (WGS84).
        width, height: mirror size, m.
        initial_orientation: mirror normal at zero joint angles (ENU; PAINT: south).
        actuators: the two entries of ``kinematics_properties.actuators`` (axis 1,
            axis 2) as dicts: ``type_axis`` (str) and numbers (int or float as in
            the file) for the keys of :data:`ACTUATOR_KEYS` that are present.
        joint_translation_1, joint_translation_2: ``joint_translation_{e,n,u}_{1,2}``, m.
        concentrator_translation: ``concentrator_translation_{e,n,u}``, m.
        facets: ``facet_properties.facets`` (empty if the file has none).
        canting_type: ``facet_properties.canting_type`` or None.
        renovation: ``renovation`` (a date or date range string) or None.
        source: the file it came from.
    """

    heliostat_id: str
    position_lla: Vec3
    width: float
    height: float
    initial_orientation: Vec3
    actuators: tuple[dict[str, Any], dict[str, Any]]
    joint_translation_1: Vec3 = (0.0, 0.0, 0.0)
    joint_translation_2: Vec3 = (0.0, 0.0, 0.0)
    concentrator_translation: Vec3 = (0.0, 0.0, 0.0)
    facets: tuple[Facet, ...] = ()
    canting_type: str | None = None
    renovation: str | None = None
    source: str = _MEMORY


@dataclasses.dataclass(frozen=True)
class CalibrationRecord:
    """One calibration record.

    Attributes:
        record_id: from the file name ``<ID>-calibration-properties.json`` (CSV: ``sample_id``).
        heliostat_id: the heliostat (directory name ``<H>/Calibration``; CSV column).
        axis_1_counts, axis_2_counts: motor positions, integer counts.
        target_name: a planar entry of the tower file.
        sun_azimuth_deg: deg, 0 = south, positive toward east.
        sun_elevation_deg: deg.
        focal_spot_helios: HeliOS centroid (WGS84) or None.
        focal_spot_utis: UTIS centroid (WGS84) or None (absent or null in the file).
        datetime: UTC ISO-8601 string from ``calibration-timestamps.json`` (CSV:
            ``timestamp``) or None when unknown.
        weather: the keys of :data:`WEATHER_KEYS` in file units; NaN = unknown.
        source: the file it came from (CSV: ``path:line``).
    """

    record_id: int
    heliostat_id: str
    axis_1_counts: int
    axis_2_counts: int
    target_name: str
    sun_azimuth_deg: float
    sun_elevation_deg: float
    focal_spot_helios: Vec3 | None
    focal_spot_utis: Vec3 | None = None
    datetime: str | None = None
    weather: dict[str, float] = dataclasses.field(default_factory=_nan_weather)
    source: str = _MEMORY


@dataclasses.dataclass(frozen=True)
class TimestampEntry:
    """An entry of ``calibration-timestamps.json``."""

    heliostat_id: str
    datetime: str


# ======================================================================================
# Validation helpers
# ======================================================================================


def _load_json(path: str | os.PathLike) -> Any:
    """Parse a JSON file; every failure becomes a DataError naming the file."""
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise DataError(path, None, f"cannot read file: {e.strerror or e}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DataError(path, None, f"not UTF-8 text (byte {e.start})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise DataError(path, None, f"malformed JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except (ValueError, RecursionError) as e:
        raise DataError(path, None, f"malformed JSON: {type(e).__name__}") from None


def _join(prefix: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{prefix}[{key}]"
    return key if not prefix else f"{prefix}.{key}"


class _Node:
    """A JSON object with typed, validating getters that name the dotted field."""

    __slots__ = ("file", "data", "prefix")

    def __init__(self, file: str, data: Any, prefix: str = ""):
        if not isinstance(data, dict):
            raise DataError(file, prefix or None, f"expected a JSON object, got {_type_name(data)}")
        self.file = file
        self.data = data
        self.prefix = prefix

    def field(self, key: str) -> str:
        return _join(self.prefix, key)

    def has(self, key: str) -> bool:
        return key in self.data

    def get(self, key: str) -> Any:
        if key not in self.data:
            raise DataError(self.file, self.field(key), "missing")
        return self.data[key]

    def node(self, key: str) -> _Node:
        return _Node(self.file, self.get(key), self.field(key))

    def number(self, key: str) -> float | int:
        return _number(self.file, self.field(key), self.get(key))

    def integer(self, key: str) -> int:
        return _integer(self.file, self.field(key), self.get(key))

    def string(self, key: str) -> str:
        v = self.get(key)
        if not isinstance(v, str):
            raise DataError(self.file, self.field(key), f"expected a string, got {_type_name(v)}")
        return v

    def vec3(self, key: str) -> Vec3:
        return _vec3(self.file, self.field(key), self.get(key))


def _type_name(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, (int, float)):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "an array"
    if isinstance(v, dict):
        return "an object"
    return type(v).__name__


def _number(file: str, field: str, v: Any) -> float | int:
    """A finite JSON number (int kept int, float kept float)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DataError(file, field, f"expected a number, got {_type_name(v)}")
    try:
        f = float(v)
    except OverflowError:
        raise DataError(file, field, "number out of range") from None
    if not math.isfinite(f):
        raise DataError(file, field, f"not finite ({v!r})")
    return v


def _integer(file: str, field: str, v: Any) -> int:
    """A finite integral JSON number, returned as int (2.0 is accepted as 2)."""
    v = _number(file, field, v)
    if isinstance(v, float):
        if not v.is_integer():
            raise DataError(file, field, f"expected an integer, got {v!r}")
        return int(v)
    return v


def _vec3(file: str, field: str, v: Any) -> Vec3:
    if not isinstance(v, list) or len(v) != 3:
        what = f"an array of {len(v)}" if isinstance(v, list) else _type_name(v)
        raise DataError(file, field, f"expected an array of 3 numbers, got {what}")
    return tuple(float(_number(file, _join(field, i), x)) for i, x in enumerate(v))  # type: ignore[return-value]


def _check(cond: bool, file: str, field: str | None, reason: str) -> None:
    if not cond:
        raise DataError(file, field, reason)


def _latlon_ok(file: str, field: str, lla: Vec3) -> None:
    _check(-90.0 <= lla[0] <= 90.0, file, field, f"latitude {lla[0]!r} outside [-90, 90] deg")
    _check(-180.0 <= lla[1] <= 360.0, file, field, f"longitude {lla[1]!r} outside [-180, 360] deg")
    _check(abs(lla[2]) <= 1e5, file, field, f"altitude {lla[2]!r} m is not near the Earth's surface")


def _record_id_from_name(path: Path) -> int:
    name = path.name
    if not name.endswith(CALIBRATION_SUFFIX) or not _ID_RE.match(name[: -len(CALIBRATION_SUFFIX)]):
        raise DataError(path, None, f"file name is not '<ID>{CALIBRATION_SUFFIX}' with a numeric ID")
    return int(name[: -len(CALIBRATION_SUFFIX)])


def _check_datetime(file: str, field: str, text: Any) -> str:
    if not isinstance(text, str):
        raise DataError(file, field, f"expected an ISO-8601 string, got {_type_name(text)}")
    try:
        t = datetime_to_unix(text)
    except (ValueError, TypeError, OverflowError) as e:
        raise DataError(file, field, f"not an ISO-8601 date-time: {text!r}") from None
    if not math.isfinite(t):
        raise DataError(file, field, f"not a finite date-time: {text!r}")
    return text


# ======================================================================================
# Tower file
# ======================================================================================


def _tower_from_json(file: str, data: Any) -> TowerFile:
    root = _Node(file, data)
    plant = root.node("power_plant_properties")
    plant_id = plant.get("ID") if plant.has("ID") else ""
    if not isinstance(plant_id, (str, int)) or isinstance(plant_id, bool):
        raise DataError(file, plant.field("ID"), f"expected a string, got {_type_name(plant_id)}")
    origin = plant.vec3("coordinates")
    _latlon_ok(file, plant.field("coordinates"), origin)
    targets: dict[str, TargetEntry] = {}
    for name, value in root.data.items():
        if name == "power_plant_properties":
            continue
        entry = _Node(file, value, name)
        ttype = entry.string("type")
        normal = entry.vec3("normal_vector") if entry.has("normal_vector") else None
        coords = entry.node("coordinates")
        points = {str(k): _vec3(file, coords.field(k), v) for k, v in coords.data.items()}
        for k, p in points.items():
            _latlon_ok(file, coords.field(k), p)
        extra = {}
        for k, v in entry.data.items():
            if k in ("type", "normal_vector", "coordinates"):
                continue
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                v = _number(file, entry.field(k), v)
            elif not (v is None or isinstance(v, (str, bool))):
                raise DataError(file, entry.field(k), f"expected a scalar, got {_type_name(v)}")
            extra[k] = v
        if ttype == "planar":
            for c in CORNERS:
                if c not in points:
                    raise DataError(file, coords.field(c), "missing (a planar target needs four corners)")
            if normal is not None and math.hypot(*normal) == 0.0:
                raise DataError(file, entry.field("normal_vector"), "zero vector")
        targets[name] = TargetEntry(name=name, type=ttype, normal=normal, points=points, extra=extra)
    tower = TowerFile(plant_id=str(plant_id), origin_lla=origin, targets=targets, source=file)
    if not tower.planar_target_names:
        raise DataError(file, None, "no planar calibration target")
    return tower


def _tower_to_json(tower: TowerFile) -> dict:
    out: dict[str, Any] = {
        "power_plant_properties": {"ID": tower.plant_id, "coordinates": list(tower.origin_lla)}
    }
    for name, t in tower.targets.items():
        entry: dict[str, Any] = {"type": t.type}
        if t.normal is not None:
            entry["normal_vector"] = list(t.normal)
        entry.update(t.extra)
        entry["coordinates"] = {k: list(p) for k, p in t.points.items()}
        out[name] = entry
    return out


def read_tower(path: str | os.PathLike) -> TowerFile:
    """Read and validate a ``<PLANT>-tower-measurements.json``.

    Every entry besides ``power_plant_properties`` is kept (the receiver too);
    ``planar`` entries must carry the four corners ``upper_left``,
    ``upper_right``, ``lower_left``, ``lower_right`` and are the calibration
    targets (:attr:`TowerFile.planar_target_names`).

    Raises:
        DataError: naming the file and the field.
    """
    file = str(path)
    return _tower_from_json(file, _load_json(path))


def write_tower(path: str | os.PathLike, tower: TowerFile) -> None:
    """Write ``tower`` as a PAINT tower file (atomically)."""
    _write_json(path, _tower_to_json(tower))


# ======================================================================================
# Heliostat properties
# ======================================================================================


def _actuator_from_json(file: str, node: _Node) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ACTUATOR_KEYS:
        if key not in ACTUATOR_REQUIRED and not node.has(key):
            continue
        if key == "type_axis":
            out[key] = node.string(key)
            _check(out[key] == "linear", file, node.field(key),
                   f"unsupported actuator type {out[key]!r} (heliojax models 'linear')")
        elif key in ("min_increment", "max_increment", "clockwise_axis_movement"):
            out[key] = node.integer(key)
        else:
            out[key] = node.number(key)
    f = node.field
    _check(out["clockwise_axis_movement"] in (0, 1), file, f("clockwise_axis_movement"), "must be 0 or 1")
    _check(out["min_increment"] < out["max_increment"], file, f("max_increment"),
           f"max_increment {out['max_increment']} is not above min_increment {out['min_increment']}")
    for key in ("increment", "offset", "pivot_radius"):
        _check(out[key] > 0, file, f(key), f"must be positive, got {out[key]!r}")
    _check(out["initial_stroke_length"] >= 0, file, f("initial_stroke_length"),
           f"must be non-negative, got {out['initial_stroke_length']!r}")
    return out


def _properties_from_json(file: str, data: Any, heliostat_id: str) -> HeliostatProperties:
    root = _Node(file, data)
    pos = root.vec3("heliostat_position")
    _latlon_ok(file, "heliostat_position", pos)
    width = float(root.number("width"))
    height = float(root.number("height"))
    _check(width > 0, file, "width", f"must be positive, got {width!r}")
    _check(height > 0, file, "height", f"must be positive, got {height!r}")
    orient = root.vec3("initial_orientation")
    norm = math.sqrt(sum(x * x for x in orient))
    _check(norm > 0, file, "initial_orientation", "zero vector")
    south = (orient[0] / norm, orient[1] / norm, orient[2] / norm)
    _check(abs(south[0]) < 1e-9 and abs(south[1] + 1.0) < 1e-9 and abs(south[2]) < 1e-9, file,
           "initial_orientation",
           f"{list(orient)} is not south [0, -1, 0], the reference pose heliojax's kinematics assume")
    kin = root.node("kinematics_properties")
    acts = kin.get("actuators")
    if not isinstance(acts, list) or len(acts) != 2:
        what = f"an array of {len(acts)}" if isinstance(acts, list) else _type_name(acts)
        raise DataError(file, kin.field("actuators"), f"expected an array of 2 actuators, got {what}")
    actuators = tuple(
        _actuator_from_json(file, _Node(file, a, _join(kin.field("actuators"), i))) for i, a in enumerate(acts)
    )

    def triple(fmt: str) -> Vec3:
        return tuple(float(kin.number(fmt.format(c))) for c in "enu")  # type: ignore[return-value]

    jt1 = triple("joint_translation_{}_1")
    jt2 = triple("joint_translation_{}_2")
    conc = triple("concentrator_translation_{}")
    facets: tuple[Facet, ...] = ()
    canting_type = None
    if root.has("facet_properties"):
        fp = root.node("facet_properties")
        if fp.has("canting_type"):
            canting_type = fp.string("canting_type")
        raw = fp.get("facets")
        if not isinstance(raw, list):
            raise DataError(file, fp.field("facets"), f"expected an array, got {_type_name(raw)}")
        fl = []
        for i, fd in enumerate(raw):
            fn = _Node(file, fd, _join(fp.field("facets"), i))
            fl.append(Facet(fn.vec3("translation_vector"), fn.vec3("canting_e"), fn.vec3("canting_n")))
        facets = tuple(fl)
        if fp.has("number_of_facets"):
            n = fp.integer("number_of_facets")
            _check(n == len(facets), file, fp.field("number_of_facets"),
                   f"says {n} but {len(facets)} facets are listed")
    renovation = None
    if root.has("renovation") and root.get("renovation") is not None:
        renovation = root.string("renovation")
    return HeliostatProperties(
        heliostat_id=heliostat_id,
        position_lla=pos,
        width=width,
        height=height,
        initial_orientation=orient,
        actuators=actuators,  # type: ignore[arg-type]
        joint_translation_1=jt1,
        joint_translation_2=jt2,
        concentrator_translation=conc,
        facets=facets,
        canting_type=canting_type,
        renovation=renovation,
        source=file,
    )


def _properties_to_json(p: HeliostatProperties) -> dict:
    kin: dict[str, Any] = {"actuators": [{k: a[k] for k in ACTUATOR_KEYS if k in a} for a in p.actuators]}
    for name, vec in (("joint_translation_{}_1", p.joint_translation_1),
                      ("joint_translation_{}_2", p.joint_translation_2),
                      ("concentrator_translation_{}", p.concentrator_translation)):
        for c, x in zip("enu", vec):
            kin[name.format(c)] = x
    out: dict[str, Any] = {
        "heliostat_position": list(p.position_lla),
        "height": p.height,
        "width": p.width,
        "initial_orientation": list(p.initial_orientation),
        "kinematics_properties": kin,
    }
    if p.facets or p.canting_type is not None:
        fp: dict[str, Any] = {}
        if p.canting_type is not None:
            fp["canting_type"] = p.canting_type
        fp["number_of_facets"] = len(p.facets)
        fp["facets"] = [
            {"translation_vector": list(f.translation_vector), "canting_e": list(f.canting_e),
             "canting_n": list(f.canting_n)}
            for f in p.facets
        ]
        out["facet_properties"] = fp
    if p.renovation is not None:
        out["renovation"] = p.renovation
    return out


def _heliostat_id_from_properties_name(path: Path) -> str:
    name = path.name
    if not name.endswith(PROPERTIES_SUFFIX) or len(name) == len(PROPERTIES_SUFFIX):
        raise DataError(path, None, f"file name is not '<H>{PROPERTIES_SUFFIX}'")
    return name[: -len(PROPERTIES_SUFFIX)]


def read_heliostat_properties(path: str | os.PathLike, *, heliostat_id: str | None = None) -> HeliostatProperties:
    """Read and validate a ``<H>-heliostat-properties.json``.

    Args:
        path: the file.
        heliostat_id: overrides the id taken from the file name.

    Raises:
        DataError: naming the file and the dotted field (e.g.
            ``kinematics_properties.actuators[0].increment``). The actuators must be
            ``linear`` with positive ``increment``, ``offset``, ``pivot_radius``,
            ``min_increment < max_increment`` and ``clockwise_axis_movement`` in {0, 1};
            ``initial_orientation`` must be south.
    """
    path = Path(path)
    hid = heliostat_id if heliostat_id is not None else _heliostat_id_from_properties_name(path)
    return _properties_from_json(str(path), _load_json(path), hid)


def write_heliostat_properties(path: str | os.PathLike, properties: HeliostatProperties) -> None:
    """Write a heliostat-properties file (atomically)."""
    _write_json(path, _properties_to_json(properties))


def validate_properties(properties: HeliostatProperties) -> HeliostatProperties:
    """Run the reader's checks on an in-memory :class:`HeliostatProperties`
    (serialise and re-parse); returns the re-parsed (equal) value.

    Raises:
        DataError: as :func:`read_heliostat_properties`, with ``properties.source``
            as the file.
    """
    try:
        data = _roundtrip(_properties_to_json(properties))
    except (TypeError, ValueError) as e:
        raise DataError(properties.source, None, f"not serialisable: {e}") from None
    return _properties_from_json(properties.source, data, properties.heliostat_id)


# ======================================================================================
# Calibration records
# ======================================================================================


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
    _check(-360.0 <= az <= 360.0, file, "sun_azimuth", f"{az!r} outside [-360, 360] deg")
    fs = root.node("focal_spot")
    spots: dict[str, Vec3 | None] = {}
    for key in ("HeliOS", "UTIS"):
        if fs.has(key) and fs.get(key) is not None:
            spots[key] = fs.vec3(key)
            _latlon_ok(file, fs.field(key), spots[key])  # type: ignore[arg-type]
        else:
            spots[key] = None
    if spots["HeliOS"] is None and spots["UTIS"] is None:
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


def check_record_context(
    record: CalibrationRecord,
    tower: TowerFile | None = None,
    properties: HeliostatProperties | Mapping[str, HeliostatProperties] | None = None,
) -> None:
    """Checks of a record against its tower file and heliostat properties.

    Raises:
        DataError: (file = ``record.source``) for a ``target_name`` that is not a
            planar target of ``tower``; for a heliostat missing from ``properties``
            (when a mapping id -> properties is given); for motor counts outside
            ``[min_increment, max_increment]``.
    """
    file = record.source
    if tower is not None:
        t = tower.targets.get(record.target_name)
        if t is None:
            raise DataError(file, "target_name",
                            f"unknown target {record.target_name!r} (tower file has "
                            f"{', '.join(tower.planar_target_names)})")
        if not t.is_planar_target:
            raise DataError(file, "target_name", f"{record.target_name!r} is not a planar calibration target")
    if properties is None:
        return
    if isinstance(properties, Mapping):
        props = properties.get(record.heliostat_id)
        if props is None:
            raise DataError(file, "heliostat_id",
                            f"heliostat {record.heliostat_id!r} has no properties file")
    else:
        props = properties
        if props.heliostat_id != record.heliostat_id:
            raise DataError(file, "heliostat_id",
                            f"record of {record.heliostat_id!r} checked against properties of "
                            f"{props.heliostat_id!r}")
    for axis, count in ((1, record.axis_1_counts), (2, record.axis_2_counts)):
        a = props.actuators[axis - 1]
        lo, hi = a["min_increment"], a["max_increment"]
        if not lo <= count <= hi:
            raise DataError(file, f"motor_position.axis_{axis}_motor_position",
                            f"count {count} outside [min_increment, max_increment] = [{lo}, {hi}] "
                            f"of {Path(props.source).name}")


def validate_record(record: CalibrationRecord) -> CalibrationRecord:
    """Run the reader's value checks on an in-memory :class:`CalibrationRecord`
    (serialise and re-parse, plus the date-time and weather); returns the
    re-parsed (equal) record.

    Raises:
        DataError: with ``record.source`` as the file.
    """
    file = record.source
    rid = record.record_id
    if isinstance(rid, bool) or not isinstance(rid, numbers.Integral) or rid < 0:
        raise DataError(file, "record_id", f"expected a non-negative integer, got {rid!r}")
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
        out[k] = math.nan if math.isnan(v) else v
    return out


def calibration_record_path(root: str | os.PathLike, heliostat_id: str, record_id: int) -> Path:
    """``root/<H>/Calibration/<ID>-calibration-properties.json``."""
    return Path(root) / heliostat_id / "Calibration" / f"{record_id}{CALIBRATION_SUFFIX}"


def heliostat_properties_path(root: str | os.PathLike, heliostat_id: str) -> Path:
    """``root/<H>/Properties/<H>-heliostat-properties.json``."""
    return Path(root) / heliostat_id / "Properties" / f"{heliostat_id}{PROPERTIES_SUFFIX}"


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
        DataError: naming the file and the dotted field.
    """
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
            raise DataError(file, "heliostat_id",
                            f"{TIMESTAMPS_FILE} assigns record {rid} to {entry.heliostat_id!r}, "
                            f"the file lies under {heliostat_id!r}")
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


# ======================================================================================
# Timestamps
# ======================================================================================


def read_timestamps(
    path: str | os.PathLike, *, on_error: Callable[[DataError], None] | None = None
) -> dict[int, TimestampEntry]:
    """Read ``calibration-timestamps.json``: record id -> (heliostat_id, UTC datetime).

    Args:
        path: the file.
        on_error: None raises the first bad entry's :class:`DataError`; a callable
            receives it and the entry is skipped.

    Raises:
        DataError: for an unreadable/malformed file (always) and bad entries
            (field ``"<ID>.datetime"`` etc.) when ``on_error`` is None.
    """
    file = str(path)
    root = _Node(file, _load_json(path))
    out: dict[int, TimestampEntry] = {}
    for key, value in root.data.items():
        try:
            if not _ID_RE.match(key):
                raise DataError(file, key, "record id is not numeric")
            entry = _Node(file, value, key)
            hid = entry.string("heliostat_id")
            _check(bool(hid), file, entry.field("heliostat_id"), "empty")
            dt = _check_datetime(file, entry.field("datetime"), entry.get("datetime"))
            out[int(key)] = TimestampEntry(hid, dt)
        except DataError as e:
            if on_error is None:
                raise
            on_error(e)
    return out


def write_timestamps(
    path: str | os.PathLike, entries: Mapping[int, TimestampEntry] | Iterable[CalibrationRecord]
) -> None:
    """Write ``calibration-timestamps.json`` (atomically), ids in ascending order.

    Args:
        entries: a mapping id -> :class:`TimestampEntry`, or records (those with a
            ``datetime`` are written).
    """
    if isinstance(entries, Mapping):
        items = {int(k): v for k, v in entries.items()}
    else:
        items = {r.record_id: TimestampEntry(r.heliostat_id, r.datetime) for r in entries if r.datetime is not None}
    data = {str(k): {"heliostat_id": items[k].heliostat_id, "datetime": items[k].datetime} for k in sorted(items)}
    _write_json(path, data, indent=1)


# ======================================================================================
# The CSV form
# ======================================================================================


def _csv_float(file: str, field: str, text: str, *, allow_empty: bool) -> float:
    s = text.strip()
    if s == "" or s.lower() == "nan":
        if allow_empty:
            return math.nan
        raise DataError(file, field, "missing (empty cell)" if s == "" else "not finite ('nan')")
    try:
        v = float(s)
    except ValueError:
        raise DataError(file, field, f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise DataError(file, field, f"not finite ({text!r})")
    return v


def _csv_int(file: str, field: str, text: str) -> int:
    s = text.strip()
    try:
        return int(s)
    except ValueError:
        pass
    v = _csv_float(file, field, text, allow_empty=False)
    if not v.is_integer():
        raise DataError(file, field, f"expected an integer, got {text!r}")
    return int(v)


def read_weather_csv(
    path: str | os.PathLike, *, on_error: Callable[[DataError], None] | None = None
) -> tuple[CalibrationRecord, ...]:
    """Read ``calibration-with-weather.csv`` (columns :data:`CSV_COLUMNS`): one
    :class:`CalibrationRecord` per row.

    The row's ``focal_spot_*`` is PAINT's HeliOS centroid (``focal_spot_utis`` is
    None), ``timestamp`` its datetime (empty: unknown), ``sample_id`` the record id,
    the weather columns its weather (empty or ``nan``: unknown). The heliostat and
    target-centre position and tracking-error columns are not used (positions come
    from the properties and tower files). The records double as the weather source
    of a directory load: ``{(r.heliostat_id, r.record_id): r.weather}``.

    Args:
        path: the CSV file.
        on_error: None raises the first bad row's :class:`DataError` (field
            ``"row <line>.<column>"``); a callable receives it and the row is skipped.

    Raises:
        DataError: unreadable file or missing columns (always); bad rows (see ``on_error``).
    """
    file = str(path)
    try:
        text = Path(path).read_bytes().decode("utf-8-sig")
    except OSError as e:
        raise DataError(file, None, f"cannot read file: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise DataError(file, None, f"not UTF-8 text (byte {e.start})") from None
    try:
        table = list(csv.reader(io.StringIO(text, newline="")))
    except csv.Error as e:
        raise DataError(file, None, f"malformed CSV: {e}") from None
    header = [h.strip() for h in table[0]] if table else []
    missing = [c for c in _CSV_REQUIRED if c not in header]
    if missing:
        raise DataError(file, missing[0], f"missing column(s): {', '.join(missing)}")
    col = {name: header.index(name) for name in set(header)}
    ncols = len(header)
    wcols = [(k, col[k]) for k in WEATHER_KEYS if k in col]
    out = []
    for line, cells in enumerate(table[1:], start=2):  # header is line 1; no multi-line cells here
        if not cells:
            continue
        where = f"row {line}"
        try:
            if len(cells) != ncols:
                raise DataError(file, where, f"{len(cells)} cells, the header has {ncols}")

            def num(name, allow_empty=False):
                return _csv_float(file, f"{where}.{name}", cells[col[name]], allow_empty=allow_empty)

            hid = cells[col["heliostat_id"]].strip()
            _check(bool(hid), file, f"{where}.heliostat_id", "missing (empty cell)")
            rid = _csv_int(file, f"{where}.sample_id", cells[col["sample_id"]])
            _check(rid >= 0, file, f"{where}.sample_id", "negative")
            ts = cells[col["timestamp"]].strip()
            dt = _check_datetime(file, f"{where}.timestamp", ts) if ts else None
            el, az = num("sun_elevation"), num("sun_azimuth")
            _check(-90.0 <= el <= 90.0, file, f"{where}.sun_elevation", f"{el!r} outside [-90, 90] deg")
            _check(-360.0 <= az <= 360.0, file, f"{where}.sun_azimuth", f"{az!r} outside [-360, 360] deg")
            c1 = _csv_int(file, f"{where}.axis_1_motor_position", cells[col["axis_1_motor_position"]])
            c2 = _csv_int(file, f"{where}.axis_2_motor_position", cells[col["axis_2_motor_position"]])
            target = cells[col["target_name"]].strip()
            _check(bool(target), file, f"{where}.target_name", "missing (empty cell)")
            spot = (num("focal_spot_lat"), num("focal_spot_lon"), num("focal_spot_alt"))
            _latlon_ok(file, f"{where}.focal_spot_lat", spot)
            weather = _nan_weather()
            for k, c in wcols:
                v = _csv_float(file, f"{where}.{k}", cells[c], allow_empty=True)
                if not math.isnan(v):
                    weather[k] = v
            out.append(
                CalibrationRecord(
                    record_id=rid, heliostat_id=hid, axis_1_counts=c1, axis_2_counts=c2, target_name=target,
                    sun_azimuth_deg=az, sun_elevation_deg=el, focal_spot_helios=spot, focal_spot_utis=None,
                    datetime=dt, weather=weather, source=f"{file}:{line}",
                )
            )
        except DataError as e:
            if on_error is None:
                raise
            on_error(e)
    return tuple(out)


def _csv_cell(v: float | None) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    return repr(float(v)) if isinstance(v, float) else str(v)


def write_weather_csv(
    path: str | os.PathLike,
    records: Iterable[CalibrationRecord],
    *,
    properties: Mapping[str, HeliostatProperties] | None = None,
    tower: TowerFile | None = None,
) -> None:
    """Write records as ``calibration-with-weather.csv`` (atomically), one row per
    record, columns :data:`CSV_COLUMNS`.

    ``focal_spot_*`` is the HeliOS centroid (UTIS where there is none);
    ``heliostat_*`` comes from ``properties`` and ``target_center_*`` from the
    target's ``center`` point in ``tower`` when given (else empty); tracking-error
    columns are empty; unknown (NaN) weather is an empty cell. Floats use ``repr``.
    """
    with atomic_write(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(CSV_COLUMNS)
        for r in records:
            spot = r.focal_spot_helios if r.focal_spot_helios is not None else r.focal_spot_utis
            p = None if properties is None else properties.get(r.heliostat_id)
            hpos = p.position_lla if p is not None else (None, None, None)
            t = None if tower is None else tower.targets.get(r.target_name)
            centre = t.points.get("center") if t is not None else None
            centre = centre if centre is not None else (None, None, None)
            row = [
                r.heliostat_id, r.datetime or "", str(r.record_id),
                _csv_cell(float(r.sun_elevation_deg)), _csv_cell(float(r.sun_azimuth_deg)),
                str(r.axis_1_counts), str(r.axis_2_counts), r.target_name,
                *(_csv_cell(x) for x in hpos),
                *(_csv_cell(x) for x in (spot if spot is not None else (None, None, None))),
                *(_csv_cell(x) for x in centre),
                "", "", "",
                *(_csv_cell(float(r.weather.get(k, math.nan))) for k in
                  ("wind_speed", "wind_direction", "dni", "temperature", "humidity", "pressure")),
            ]
            w.writerow(row)


# ======================================================================================
# Directory writer
# ======================================================================================


def _json_default(v: Any) -> Any:
    """numpy scalars and arrays (e.g. from a simulator) -> plain Python values."""
    if hasattr(v, "tolist") and callable(v.tolist):
        return v.tolist()
    raise TypeError(f"{type(v).__name__} is not JSON serialisable")


def _roundtrip(data: Any) -> Any:
    return json.loads(json.dumps(data, default=_json_default))


def _write_json(path: str | os.PathLike, data: Any, indent: int = 2) -> None:
    text = json.dumps(data, indent=indent, allow_nan=False, default=_json_default)
    with atomic_write(path, "w") as f:
        f.write(text)


def write_paint_directory(
    out_dir: str | os.PathLike,
    tower: TowerFile,
    properties: Sequence[HeliostatProperties],
    records: Sequence[CalibrationRecord],
    weather: bool = True,
) -> Path:
    """Write a PAINT-layout directory that :func:`heliojax.load_paint_directory` reads
    back unchanged (bit-identical arrays to :func:`heliojax.records_to_fleet` on the
    same inputs).

    Layout: ``<plant_id or "plant">-tower-measurements.json``,
    ``<H>/Properties/<H>-heliostat-properties.json``,
    ``<H>/Calibration/<ID>-calibration-properties.json``,
    ``calibration-timestamps.json`` (records with a datetime) and, when ``weather``
    is true and any record has a known weather value,
    ``calibration-with-weather.csv`` (one row per such record). Every file is
    written atomically; existing files of the same names are replaced, others
    are left alone.

    Args:
        out_dir: the directory (created).
        tower: the tower file.
        properties: one per heliostat.
        records: calibration records (each needs a non-negative ``record_id``, unique).
        weather: write the weather CSV.

    Returns:
        ``out_dir`` as a Path.

    Raises:
        DataError: for values the readers would reject (checked before anything is
            written) and duplicate record ids.
    """
    out = Path(out_dir)
    # Validate first so that a bad input leaves no half-written directory behind.
    try:
        _tower_from_json(tower.source, _roundtrip(_tower_to_json(tower)))
    except (TypeError, ValueError) as e:
        if isinstance(e, DataError):
            raise
        raise DataError(tower.source, None, f"not serialisable: {e}") from None
    props = [validate_properties(p) for p in properties]
    seen: set[int] = set()
    for r in records:
        validate_record(r)
        if r.record_id in seen:
            raise DataError(r.source, "record_id", f"duplicate record id {r.record_id}")
        seen.add(r.record_id)
    out.mkdir(parents=True, exist_ok=True)
    write_tower(out / f"{tower.plant_id or 'plant'}{TOWER_FILE_SUFFIX}", tower)
    for p in props:
        write_heliostat_properties(heliostat_properties_path(out, p.heliostat_id), p)
    for r in records:
        write_calibration_record(calibration_record_path(out, r.heliostat_id, r.record_id), r)
    write_timestamps(out / TIMESTAMPS_FILE, records)
    with_weather = [r for r in records if any(not math.isnan(float(v)) for v in r.weather.values())]
    if weather and with_weather:
        write_weather_csv(out / WEATHER_CSV_FILE, with_weather,
                          properties={p.heliostat_id: p for p in props}, tower=tower)
    return out
