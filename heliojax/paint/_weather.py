"""``calibration-with-weather.csv``: records with weather columns (a third-party join)."""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Callable, Iterable, Mapping
from typing import no_type_check

from .._errors import DataError
from .._io import atomic_write, is_decimal
from ._common import (
    _CSV_REQUIRED,
    CSV_COLUMNS,
    RECORD_ID_LIMIT,
    WEATHER_KEYS,
    CalibrationRecord,
    HeliostatProperties,
    TowerFile,
    _check,
    _check_datetime,
    _check_weather_value,
    _csv_cells,
    _csv_table,
    _latlon_ok,
    _nan_weather,
)

# ======================================================================================
# The CSV form
# ======================================================================================


@no_type_check
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
    if not is_decimal(s):
        raise DataError(file, field, f"not a decimal number: {text!r}")
    return v


@no_type_check
def _csv_int(file: str, field: str, text: str) -> int:
    s = text.strip()
    if is_decimal(s):
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
    file, header, rows = _csv_table(path, _CSV_REQUIRED, CSV_COLUMNS)
    col = {name: header.index(name) for name in set(header)}
    ncols = len(header)
    wcols = [(k, col[k]) for k in WEATHER_KEYS if k in col]
    out = []
    for line, text_line in rows:
        where = f"row {line}"
        try:
            cells = _csv_cells(file, where, text_line, ncols)
            if cells is None:
                continue

            @no_type_check
            def num(name, allow_empty=False):
                return _csv_float(file, f"{where}.{name}", cells[col[name]], allow_empty=allow_empty)

            hid = cells[col["heliostat_id"]].strip()
            _check(bool(hid), file, f"{where}.heliostat_id", "missing (empty cell)")
            _check(
                hid.isprintable(),
                file,
                f"{where}.heliostat_id",
                f"{hid[:40]!r} is not a heliostat id (control characters)",
            )
            rid = _csv_int(file, f"{where}.sample_id", cells[col["sample_id"]])
            _check(
                0 <= rid < RECORD_ID_LIMIT, file, f"{where}.sample_id", f"expected an integer in [0, 2**31), got {rid}"
            )
            ts = cells[col["timestamp"]].strip()
            dt = _check_datetime(file, f"{where}.timestamp", ts) if ts else None
            el, az = num("sun_elevation"), num("sun_azimuth")
            _check(-90.0 <= el <= 90.0, file, f"{where}.sun_elevation", f"{el!r} outside [-90, 90] deg")
            _check(
                el > 0.0,
                file,
                f"{where}.sun_elevation",
                f"{el!r} deg: the sun is below the horizon (no reflection to measure)",
            )
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
                _check_weather_value(file, f"{where}.{k}", k, v)
                if not math.isnan(v):
                    weather[k] = v
            out.append(
                CalibrationRecord(
                    record_id=rid,
                    heliostat_id=hid,
                    axis_1_counts=c1,
                    axis_2_counts=c2,
                    target_name=target,
                    sun_azimuth_deg=az,
                    sun_elevation_deg=el,
                    focal_spot_helios=spot,
                    focal_spot_utis=None,
                    datetime=dt,
                    weather=weather,
                    source=f"{file}:{line}",
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
                r.heliostat_id,
                r.datetime or "",
                str(r.record_id),
                _csv_cell(float(r.sun_elevation_deg)),
                _csv_cell(float(r.sun_azimuth_deg)),
                str(r.axis_1_counts),
                str(r.axis_2_counts),
                r.target_name,
                *(_csv_cell(x) for x in hpos),
                *(_csv_cell(x) for x in (spot if spot is not None else (None, None, None))),
                *(_csv_cell(x) for x in centre),
                "",
                "",
                "",
                *(
                    _csv_cell(float(r.weather.get(k, math.nan)))
                    for k in ("wind_speed", "wind_direction", "dni", "temperature", "humidity", "pressure")
                ),
            ]
            w.writerow(row)
