"""PAINT files: raw, validated Python records and their writers.

This subpackage is the data boundary of heliojax: nothing else opens PAINT files. It reads (and writes, atomically)
the files of a PAINT download directory::

    <PLANT>-tower-measurements.json                   tower, calibration targets, receiver
    <H>/Properties/<H>-heliostat-properties.json      one per heliostat
    <H>/Calibration/<ID>-calibration-properties.json  one per calibration record
    calibration-timestamps.json                       <ID> -> {heliostat_id, datetime (UTC)}
    calibration-with-weather.csv                      optional: one row per record, with weather

and ARTIST's scenario HDF5 files (:func:`read_artist_scenario`,
:func:`write_artist_scenario`), into frozen dataclasses of plain Python values (:class:`TowerFile`,
:class:`HeliostatProperties`, :class:`CalibrationRecord`). Units are those of
the files: WGS84 ``[lat_deg, lon_deg, alt_m]`` positions, degrees for the sun
(PAINT azimuth: 0 = south, positive toward east), metres and radians for the
actuators, motor positions in integer stepper counts. The conversion to the
ENU frame and to arrays (a :class:`heliojax.Fleet`) happens in :func:`load_paint_directory`.

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

import importlib as _importlib
import typing as _typing

from ._calibration import (
    calibration_record_path as calibration_record_path,
    check_record_context as check_record_context,
    heliostat_properties_path as heliostat_properties_path,
    read_calibration_record as read_calibration_record,
    validate_record as validate_record,
    write_calibration_record as write_calibration_record,
)
from ._common import (
    ACTUATOR_KEYS as ACTUATOR_KEYS,
    ACTUATOR_OPTIONAL as ACTUATOR_OPTIONAL,
    ACTUATOR_REQUIRED as ACTUATOR_REQUIRED,
    CALIBRATION_SUFFIX as CALIBRATION_SUFFIX,
    CORNERS as CORNERS,
    CSV_COLUMNS as CSV_COLUMNS,
    PROPERTIES_SUFFIX as PROPERTIES_SUFFIX,
    TIMESTAMPS_FILE as TIMESTAMPS_FILE,
    TOWER_FILE_SUFFIX as TOWER_FILE_SUFFIX,
    WEATHER_CSV_FILE as WEATHER_CSV_FILE,
    WEATHER_KEYS as WEATHER_KEYS,
    CalibrationRecord as CalibrationRecord,
    Facet as Facet,
    HeliostatProperties as HeliostatProperties,
    TargetEntry as TargetEntry,
    TimestampEntry as TimestampEntry,
    TowerFile as TowerFile,
    Vec3 as Vec3,
)
from ._directory import (
    write_paint_directory as write_paint_directory,
)
from ._load import (
    default_data_dir as default_data_dir,
    load_paint_directory as load_paint_directory,
    load_weather_csv_fleet as load_weather_csv_fleet,
    records_to_fleet as records_to_fleet,
)
from ._properties import (
    read_facets as read_facets,
    read_heliostat_properties as read_heliostat_properties,
    validate_properties as validate_properties,
    write_heliostat_properties as write_heliostat_properties,
)
from ._timestamps import (
    read_timestamps as read_timestamps,
    write_timestamps as write_timestamps,
)
from ._tower import (
    read_tower as read_tower,
    write_tower as write_tower,
)
from ._weather import (
    read_weather_csv as read_weather_csv,
    write_weather_csv as write_weather_csv,
)

# Loaded on first use (PEP 562): the STAC client (pystac, requests), PNG (Pillow) and
# HDF5 (h5py) readers cost ~0.15 s of import that loading a PAINT directory never needs.
_LAZY = {
    "ACTUATOR_PARAMETERS": "_artist",
    "DEVIATIONS": "_artist",
    "ArtistActuator": "_artist",
    "ArtistFacet": "_artist",
    "ArtistHeliostat": "_artist",
    "ArtistLightSource": "_artist",
    "ArtistPlanarTarget": "_artist",
    "ArtistScenario": "_artist",
    "read_artist_scenario": "_artist",
    "write_artist_scenario": "_artist",
    "read_deflectometry_facets": "_deflectometry",
    "write_deflectometry": "_deflectometry",
    "MAX_FLUX_PIXELS": "_flux",
    "read_flux_png": "_flux",
    "fetch_catalog": "_stac",
    "verify_download": "_stac",
    "CALIBRATION_ASSETS": "_stac_io",
    "COLLECTIONS": "_stac_io",
    "JOURNAL_NAME": "_stac_io",
    "FetchReport": "_stac_io",
}

if _typing.TYPE_CHECKING:
    from ._artist import (
        ACTUATOR_PARAMETERS as ACTUATOR_PARAMETERS,
        DEVIATIONS as DEVIATIONS,
        ArtistActuator as ArtistActuator,
        ArtistFacet as ArtistFacet,
        ArtistHeliostat as ArtistHeliostat,
        ArtistLightSource as ArtistLightSource,
        ArtistPlanarTarget as ArtistPlanarTarget,
        ArtistScenario as ArtistScenario,
        read_artist_scenario as read_artist_scenario,
        write_artist_scenario as write_artist_scenario,
    )
    from ._deflectometry import (
        read_deflectometry_facets as read_deflectometry_facets,
        write_deflectometry as write_deflectometry,
    )
    from ._flux import MAX_FLUX_PIXELS as MAX_FLUX_PIXELS, read_flux_png as read_flux_png
    from ._stac import (
        fetch_catalog as fetch_catalog,
        verify_download as verify_download,
    )
    from ._stac_io import (
        CALIBRATION_ASSETS as CALIBRATION_ASSETS,
        COLLECTIONS as COLLECTIONS,
        JOURNAL_NAME as JOURNAL_NAME,
        FetchReport as FetchReport,
    )


def __getattr__(name: str) -> _typing.Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(_importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
