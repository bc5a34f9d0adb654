"""Writing a whole PAINT download directory (simulations, round-trip tests)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

from .._errors import DataError
from .._io import shown_value
from ._calibration import calibration_record_path, heliostat_properties_path, validate_record, write_calibration_record
from ._common import (
    TIMESTAMPS_FILE,
    TOWER_FILE_SUFFIX,
    WEATHER_CSV_FILE,
    CalibrationRecord,
    HeliostatProperties,
    TowerFile,
    _roundtrip,
)
from ._properties import validate_properties, write_heliostat_properties
from ._timestamps import write_timestamps
from ._tower import _tower_from_json, _tower_to_json, write_tower
from ._weather import write_weather_csv


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
        checked = _tower_from_json(tower.source, _roundtrip(_tower_to_json(tower)))
    except (TypeError, ValueError) as e:
        if isinstance(e, DataError):
            raise
        raise DataError(tower.source, None, f"not serialisable: {e}") from None
    if checked.skipped:  # a target the reader would skip: not written
        name, problem = next(iter(checked.skipped.items()))
        raise DataError(tower.source, shown_value(name), f"not a target name ({problem})")
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
        write_weather_csv(
            out / WEATHER_CSV_FILE, with_weather, properties={p.heliostat_id: p for p in props}, tower=tower
        )
    return out
