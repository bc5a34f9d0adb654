"""Shared pieces of the PAINT readers: file names, the record types (frozen
dataclasses of file values), validation helpers and the JSON writer."""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import math
import os
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, no_type_check

from .._errors import DataError
from .._io import atomic_write, check_path_argument, input_file_problem
from .._sun import datetime_to_unix

Vec3 = tuple[float, float, float]

TOWER_FILE_SUFFIX = "-tower-measurements.json"
"""File-name suffix of the tower file (``<PLANT>-tower-measurements.json``)."""
TIMESTAMPS_FILE = "calibration-timestamps.json"
WEATHER_CSV_FILE = "calibration-with-weather.csv"
PROPERTIES_SUFFIX = "-heliostat-properties.json"
CALIBRATION_SUFFIX = "-calibration-properties.json"

ACTUATOR_TYPES = ("linear", "ideal")
"""Actuator kinds heliojax models: ``linear`` (the law of cosines of the stroke) and
``ideal`` (joint angle linear in the counts, :attr:`heliojax.HeliostatGeometry.ideal_axes`)."""

WEATHER_KEYS = ("temperature", "wind_speed", "wind_direction", "dni", "humidity", "pressure")
"""Weather of a record (file units: deg C, m/s, deg, W/m^2, %, hPa); NaN = unknown."""
WEATHER_RANGES = {
    "temperature": (-90.0, 60.0, "deg C"),
    "wind_speed": (0.0, 120.0, "m/s"),
    "wind_direction": (-360.0, 360.0, "deg"),
    "dni": (0.0, 1500.0, "W/m^2"),
    "humidity": (0.0, 100.0, "%"),
    "pressure": (300.0, 1100.0, "hPa"),
}
"""Physically possible weather at a plant on the ground (file units); a value outside
(a negative wind speed, a temperature of 1e308, a pressure in Pa) is not a measurement."""

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

MAX_COUNTS = 2**31 - 1
"""Largest magnitude of a motor count (``min_increment``, ``max_increment``): an
actuator's encoder position is a 32-bit register (PAINT's counts stay below 80 000)."""
MAX_ACTUATOR_LENGTH_M = 10.0
"""Longest side of an actuator triangle (``offset``, ``pivot_radius``), stroke at count
0 and stroke travel over the count range, m (PAINT: 0.07-0.49 m; a heliostat is at most
:data:`MAX_HELIOSTAT_SIZE_M` across, its actuators far less)."""

ACTUATOR_BOUNDS = (
    ("increment", "positive", 1e3, 1e8, "counts/m"),
    ("offset", "positive", 1e-2, MAX_ACTUATOR_LENGTH_M, "m"),
    ("pivot_radius", "positive", 1e-2, MAX_ACTUATOR_LENGTH_M, "m"),
    ("initial_stroke_length", "non-negative", 0.0, MAX_ACTUATOR_LENGTH_M, "m"),
    ("initial_angle", "", -2 * math.pi, 2 * math.pi, "rad"),
    ("min_increment", "", -MAX_COUNTS, MAX_COUNTS, "counts"),
    ("max_increment", "", -MAX_COUNTS, MAX_COUNTS, "counts"),
)
"""Bounds of an actuator's numbers: ``(key, sign, low, high, unit)``. The sign is what
the geometry needs (a pivot radius of 0 has no triangle); ``[low, high]`` is what a
heliostat's actuator can physically be: counts per metre of stroke from 1e3 (a 1 mm
step, too coarse to point within a mrad) to 1e8 (a 10 nm step), triangle sides from
1 cm to :data:`MAX_ACTUATOR_LENGTH_M`, the joint angle at count 0 within a turn,
counts within :data:`MAX_COUNTS` (PAINT's: 154 167 counts/m, sides 0.32-0.34 m,
strokes 0.07-0.24 m, angles -0.22-0.97 rad, counts 0-76 112). A pivot
radius of 1e-300 m or a count limit of -1e12 kept the signs and was aimed with.
With ``min_increment < max_increment``, a stroke travel over the count range of at
most :data:`MAX_ACTUATOR_LENGTH_M` and ``clockwise_axis_movement`` in {0, 1} the
bounds of :func:`actuator_problem`, which the properties reader and ``load_results``
share (:func:`actuator_bounds_kept` is the vectorised screen)."""

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
_ID_RE = re.compile(r"[0-9]{1,18}\Z")  # ASCII digits only, no trailing line break, fits int64


# The per-field scalar helpers below are ``@no_type_check``: they carry no array
# types, and the tests' run-time type checks (jaxtyping's import hook) would cost
# them ~10 s per directory load.
@no_type_check
def requested_heliostats(heliostats: Iterable[str] | str, caller: str) -> list[str]:
    """The ids of a ``heliostats`` argument: one id (a string) or an iterable of ids.
    A string was iterated over ("BF09" requested heliostats B, F, 0 and 9); anything
    else is a TypeError naming ``caller``'s argument."""
    if isinstance(heliostats, str):
        return [heliostats]
    if isinstance(heliostats, (bytes, os.PathLike)) or not isinstance(heliostats, Iterable):
        raise TypeError(
            f"{caller}: heliostats: expected a heliostat id or a list of them, got {type(heliostats).__name__}"
        )
    ids = list(heliostats)
    bad = next((x for x in ids if not isinstance(x, str)), None)
    if bad is not None:
        raise TypeError(f"{caller}: heliostats: {bad!r} ({type(bad).__name__}) is not a heliostat id (a string)")
    return ids


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
    @no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
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
        skipped: name -> why it is no target name
            (:func:`heliojax._limits.target_name_problem`) of the entries the reader
            skipped (:func:`heliojax.paint.read_tower`). Not compared.
    """

    plant_id: str
    origin_lla: Vec3
    targets: dict[str, TargetEntry]
    source: str = _MEMORY
    skipped: dict[str, str] = dataclasses.field(default_factory=dict, compare=False)

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
        notes: ``(field, reason)`` of what the reader read other than as written (an
            older PAINT version's key or label); the loader flags them. Not compared.
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
    notes: tuple[tuple[str, str], ...] = dataclasses.field(default=(), compare=False)


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
        notes: ``(field, reason)`` of what the reader read other than as written (a
            centroid that is not finite, read as missing); the loader flags them. Not
            compared.
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
    notes: tuple[tuple[str, str], ...] = dataclasses.field(default=(), compare=False)


@dataclasses.dataclass(frozen=True)
class TimestampEntry:
    """An entry of ``calibration-timestamps.json``."""

    heliostat_id: str
    datetime: str


# ======================================================================================
# Validation helpers
# ======================================================================================


class _DuplicateKeyError(ValueError):
    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


_TWICE = "listed twice with different values (which one holds is ambiguous)"
AMBIGUOUS = object()
"""The value of a JSON key given twice with different values (see :func:`_load_json`)."""


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _unique_keys(pairs: list[tuple[str, Any]], *, mark: bool = False) -> dict[str, Any]:
    """A JSON object's dict; a key given twice with different values (the json module
    would silently keep the last) is an error, or with ``mark`` holds :data:`AMBIGUOUS`."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out and out[key] != value:
            if not mark:
                raise _DuplicateKeyError(key)
            value = AMBIGUOUS
        out[key] = value
    return out


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _read_regular_file(path: str | os.PathLike) -> bytes:
    """The bytes of a regular file; a device, pipe or socket in its place (a link to
    /dev/zero reads forever, a pipe blocks), a file over :data:`~heliojax._io.MAX_INPUT_BYTES`
    and an
    unreadable file are DataErrors; a ``path`` that is no path (an int, read as a file
    descriptor; None) is a TypeError (:func:`~heliojax._io.check_path_argument`)."""
    check_path_argument(path)
    try:
        problem = input_file_problem(path)
        if problem is not None:
            raise DataError(path, None, problem)
        return Path(path).read_bytes()
    except OSError as e:
        raise DataError(path, None, f"cannot read file: {e.strerror or e}") from None


_LINE_END = re.compile(r"\r\n|\r|\n")
"""The line ends the csv module knows."""


def _csv_table(
    path: str | os.PathLike, required: Sequence[str], unique: Sequence[str]
) -> tuple[str, list[str], list[tuple[int, str]]]:
    """A CSV file's header and its rows, one a line (PAINT's CSVs have no multi-line
    cells), for :func:`_csv_cells` to parse each alone: a row the csv module refuses (a
    cell over its field limit, a quote left open) or with a byte that is not UTF-8 is
    that row's error, not the file's.

    Returns:
        ``(file, header, rows)``: ``rows`` are ``(n, line)``, ``n`` the line number
        that names it (``"row <n>"``; the header is row 1). A byte that is not UTF-8
        stays in its line as a lone surrogate (``surrogateescape``), which
        :func:`_csv_cells` refuses.

    Raises:
        DataError: an unreadable file, a header that is not UTF-8 or malformed, a
            ``required`` column missing or a column of ``unique`` given twice.
    """
    file = str(path)
    text = _read_regular_file(path).decode("utf-8-sig", errors="surrogateescape")
    lines = _LINE_END.split(text)
    bad = _not_utf8_at(lines[0])
    if bad is not None:
        raise DataError(file, "row 1", f"the header is not UTF-8 text (byte {bad})")
    try:
        header = [h.strip() for h in next(csv.reader(lines[:1]), [])]
    except csv.Error as e:
        raise DataError(file, "row 1", f"malformed CSV header: {e}") from None
    missing = [c for c in required if c not in header]
    if missing:
        raise DataError(file, missing[0], f"missing column(s): {', '.join(missing)}")
    twice = sorted({c for c in header if c in unique and header.count(c) > 1})
    if twice:
        raise DataError(file, twice[0], f"column(s) {', '.join(twice)} given twice (which one holds is ambiguous)")
    return file, header, list(enumerate(lines[1:], start=2))


_ESCAPED_BYTE = re.compile("[\udc80-\udcff]")


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _not_utf8_at(line: str) -> int | None:
    """The offset (bytes from the line's start) of the first byte of ``line`` that is
    not UTF-8 (decoded with ``surrogateescape``: a lone surrogate U+DC80-U+DCFF), or None."""
    m = _ESCAPED_BYTE.search(line)
    return None if m is None else len(line[: m.start()].encode("utf-8", "surrogateescape"))


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _csv_cells(file: str, where: str, line: str, n_columns: int) -> list[str] | None:
    """The cells of one row of :func:`_csv_table` (None for a blank line).

    Raises:
        DataError: a row with a byte that is not UTF-8, a malformed row, or one of
            another number of cells than ``n_columns``.
    """
    bad = _not_utf8_at(line)
    if bad is not None:
        raise DataError(file, where, f"not UTF-8 text (byte {bad} of the row)")
    try:
        # strict: a quote left open is a cell going on past its line (its rest, the next
        # line, was named alone while this part was read as the row), a stray one an error
        cells = next(csv.reader([line], strict=True), [])
    except csv.Error as e:
        raise DataError(file, where, f"malformed CSV row: {e}") from None
    if not cells:
        return None
    if len(cells) != n_columns:
        raise DataError(file, where, f"{len(cells)} cells, the header has {n_columns}")
    return cells


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _load_json(path: str | os.PathLike, *, mark_ambiguous: bool = False) -> Any:
    """Parse a JSON file; every failure becomes a DataError naming the file. A key given
    twice with different values is one too, or, with ``mark_ambiguous`` (a file of
    independent entries, where one bad entry must not spoil the others), holds
    :data:`AMBIGUOUS`, which :class:`_Node` reports as that entry's error."""
    raw = _read_regular_file(path)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DataError(path, None, f"not UTF-8 text (byte {e.start})") from None
    try:
        return json.loads(text, object_pairs_hook=functools.partial(_unique_keys, mark=mark_ambiguous))
    except json.JSONDecodeError as e:
        raise DataError(path, None, f"malformed JSON: {e.msg} at line {e.lineno} column {e.colno}") from None
    except _DuplicateKeyError as e:
        raise DataError(path, e.key, _TWICE) from None
    except (ValueError, RecursionError) as e:
        raise DataError(path, None, f"malformed JSON: {type(e).__name__}") from None


@no_type_check
def _join(prefix: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{prefix}[{key}]"
    return key if not prefix else f"{prefix}.{key}"


@no_type_check
class _Node:
    """A JSON object with typed, validating getters that name the dotted field."""

    __slots__ = ("file", "data", "prefix")

    def __init__(self, file: str, data: Any, prefix: str = ""):
        if data is AMBIGUOUS:
            raise DataError(file, prefix or None, _TWICE)
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
        if self.data[key] is AMBIGUOUS:
            raise DataError(
                self.file, self.field(key), "listed twice with different values (which one holds is ambiguous)"
            )
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


@no_type_check
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


@no_type_check
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


@no_type_check
def _integer(file: str, field: str, v: Any) -> int:
    """A finite integral JSON number, returned as int (2.0 is accepted as 2)."""
    v = _number(file, field, v)
    if isinstance(v, float):
        if not v.is_integer():
            raise DataError(file, field, f"expected an integer, got {v!r}")
        return int(v)
    return v


@no_type_check
def _vec3(file: str, field: str, v: Any) -> Vec3:
    if not isinstance(v, list) or len(v) != 3:
        what = f"an array of {len(v)}" if isinstance(v, list) else _type_name(v)
        raise DataError(file, field, f"expected an array of 3 numbers, got {what}")
    return tuple(float(_number(file, _join(field, i), x)) for i, x in enumerate(v))  # type: ignore[return-value]


RECORD_ID_LIMIT = 2**31
"""Record ids are integers in ``[0, RECORD_ID_LIMIT)`` (they are stored as int32)."""


@no_type_check
def _check(cond: bool, file: str, field: str | None, reason: str) -> None:
    if not cond:
        raise DataError(file, field, reason)


def _actuator_checks(a: dict[str, Any]) -> list[tuple[str, Any, Any]]:
    """The bounds of an actuator in the order they are reported: ``(key, kept, reason)``
    with ``kept`` elementwise over ``a``'s values (numbers or arrays) and ``reason()`` the
    message for a scalar actuator that breaks it. One table for
    :func:`actuator_problem` (the first broken one, named) and
    :func:`actuator_bounds_kept` (a whole fleet screened at once)."""
    import numpy as np

    # plain operators: Python numbers stay Python numbers (the reader checks one actuator
    # at a time, ~10x faster than through numpy), arrays stay arrays
    c = a["clockwise_axis_movement"]
    checks: list[tuple[str, Any, Any]] = [("clockwise_axis_movement", (c == 0) | (c == 1), lambda: "must be 0 or 1")]
    for key, sign, low, high, unit in ACTUATOR_BOUNDS:
        v = a[key]
        if sign:
            kept = v > 0 if sign == "positive" else v >= 0
            checks.append((key, kept, lambda key=key, sign=sign: f"must be {sign}, got {a[key]!r}"))
        checks.append(
            (
                key,
                (low <= v) & (v <= high),
                lambda key=key, low=low, high=high, unit=unit: (
                    f"{a[key]!r} {unit} is outside [{low:g}, {high:g}] {unit}: not a heliostat actuator's"
                ),
            )
        )
    lo, hi = a["min_increment"], a["max_increment"]
    checks.append(
        (
            "max_increment",
            lo < hi,
            lambda: f"max_increment {a['max_increment']} is not above min_increment {a['min_increment']}",
        )
    )
    with np.errstate(all="ignore"):
        travel = np.divide(np.subtract(hi, lo, dtype=np.float64), a["increment"])
    checks.append(
        (
            "max_increment",
            travel <= MAX_ACTUATOR_LENGTH_M,
            lambda: (
                f"the count range is a stroke travel of {float(travel):.4g} m, more than {MAX_ACTUATOR_LENGTH_M:g} m: "
                "not a heliostat actuator's"
            ),
        )
    )
    return checks


@no_type_check
def actuator_problem(a: dict[str, Any]) -> tuple[str, str] | None:
    """The first bound of :data:`ACTUATOR_BOUNDS` (or ``min_increment < max_increment``,
    the stroke travel, ``clockwise_axis_movement`` in {0, 1}) that the actuator ``a``
    (PAINT keys, finite numbers) breaks, as ``(key, reason)``; None when it keeps them all."""
    for key, kept, reason in _actuator_checks(a):
        if not bool(kept):
            return key, reason()
    return None


def actuator_bounds_kept(a: dict[str, Any]) -> Any:
    """Elementwise over the actuator(s) ``a`` (PAINT keys; numbers or arrays): whether
    :func:`actuator_problem` finds nothing (one vectorised screen of a whole fleet)."""
    import numpy as np

    kept = np.asarray(True)
    for _, ok, _ in _actuator_checks(a):
        kept = kept & ok
    return np.asarray(kept)


@no_type_check
def _check_weather_value(file: str, field: str, key: str, v: float) -> None:
    """A known (not NaN) weather value ``key`` must lie in :data:`WEATHER_RANGES`."""
    lo, hi, unit = WEATHER_RANGES[key]
    _check(math.isnan(v) or lo <= v <= hi, file, field, f"{v!r} {unit} outside [{lo:g}, {hi:g}] {unit}: not a {key}")


@no_type_check
def _latlon_ok(file: str, field: str, lla: Vec3) -> None:
    _check(-90.0 <= lla[0] <= 90.0, file, field, f"latitude {lla[0]!r} outside [-90, 90] deg")
    _check(-180.0 <= lla[1] <= 360.0, file, field, f"longitude {lla[1]!r} outside [-180, 360] deg")
    _check(abs(lla[2]) <= 1e5, file, field, f"altitude {lla[2]!r} m is not near the Earth's surface")


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _local_offset_m(a: Vec3, b: Vec3) -> Vec3:
    """(east, north, up) offset (m) of the WGS84 point ``a`` [lat_deg, lon_deg, alt_m] from
    ``b``, local flat-Earth approximation (good to a fraction of a percent over a plant;
    used for sanity bounds)."""
    north = math.radians(a[0] - b[0]) * 6_371_000.0
    east = math.radians((a[1] - b[1] + 180.0) % 360.0 - 180.0) * 6_371_000.0 * math.cos(math.radians(b[0]))
    return east, north, a[2] - b[2]


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _distance_m(a: Vec3, b: Vec3) -> float:
    """Distance (m) of two WGS84 points [lat_deg, lon_deg, alt_m] (:func:`_local_offset_m`)."""
    return math.hypot(*_local_offset_m(a, b))


MAX_SPOT_DISTANCE_M = 1_000.0
"""A focal spot farther than this from its target's centre is not a measurement of that target."""
MAX_HELIOSTAT_DISTANCE_M = 50_000.0
"""A heliostat farther than this from the plant's reference point is not part of the plant."""
MAX_HELIOSTAT_HEIGHT_M = 1_000.0
"""A heliostat more than this above or below the plant's reference point is not on the
plant's ground (the tallest solar towers are about 260 m; an altitude given in feet, or
from another datum, is off by more)."""
MAX_HELIOSTAT_SIZE_M = 100.0
"""A heliostat's width, height and every mount offset (joint and concentrator
translations) are at most this: the largest heliostats built are about 12 m across; a
width of 1e6 m or a translation of 1e308 m is not a heliostat."""
MAX_SUN_GAP_DEG = 2.0
"""A stored sun direction farther than this from the sun computed for the record's time
at its heliostat is not the sun of that record (real PAINT data: within 0.03 deg; a sun
given in radians, or from another day or hour, is off by far more)."""
SUN_FLAG_DEG = 0.1
"""A stored sun farther than this (but within :data:`MAX_SUN_GAP_DEG`) from the sun
computed for the record's time is kept and flagged: real PAINT suns lie within 0.03 deg;
one rounded to whole degrees is off by up to 0.7 deg (12 mrad, many times a tracking error)."""


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _record_id_from_name(path: Path) -> int:
    name = path.name
    if not name.endswith(CALIBRATION_SUFFIX) or not _ID_RE.match(name[: -len(CALIBRATION_SUFFIX)]):
        raise DataError(path, None, f"file name is not '<ID>{CALIBRATION_SUFFIX}' with a numeric ID")
    return int(name[: -len(CALIBRATION_SUFFIX)])


@no_type_check
def _check_datetime(file: str, field: str, text: Any) -> str:
    if not isinstance(text, str):
        raise DataError(file, field, f"expected an ISO-8601 string, got {_type_name(text)}")
    try:
        t = datetime_to_unix(text)
    except (ValueError, TypeError, OverflowError):
        raise DataError(file, field, f"not an ISO-8601 date-time: {text!r}") from None
    if not math.isfinite(t):
        raise DataError(file, field, f"not a finite date-time: {text!r}")
    return text


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
