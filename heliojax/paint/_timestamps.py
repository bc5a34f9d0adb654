"""Record times: ``calibration-timestamps.json`` (record id -> heliostat id and UTC
time) and, where a download has none, the calibration metadata CSV that PAINT's own
STAC client writes (``metadata/calibration_metadata_<description>.csv``)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping
from typing import no_type_check

from .._errors import DataError
from .._sun import utc_datetime
from ._common import (
    _ID_RE,
    CalibrationRecord,
    TimestampEntry,
    _check,
    _check_datetime,
    _csv_cells,
    _csv_table,
    _load_json,
    _Node,
    _write_json,
)

METADATA_GLOB = "metadata/calibration_metadata_*.csv"
"""Where PAINT's STAC client (``StacClient.get_heliostat_metadata``) writes the
calibration items' metadata, relative to its download folder: one row per record,
columns ``Id`` (the record id), ``HeliostatId``, ``DateTime`` (the item's UTC
datetime, as pandas writes it: ``2023-08-01 10:00:00+00:00``) and the sun and target
columns, which the record files hold too."""

METADATA_COLUMNS = ("Id", "HeliostatId", "DateTime")
"""The columns of the metadata CSV that :func:`read_metadata_times` reads."""

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
    root = _Node(file, _load_json(path, mark_ambiguous=True))
    out: dict[int, TimestampEntry] = {}
    ambiguous: set[int] = set()  # ids written twice (e.g. "7" and "07") with different entries
    for key, value in root.data.items():
        try:
            if not _ID_RE.match(key):
                raise DataError(file, key, "record id is not numeric")
            entry = _Node(file, value, key)
            hid = entry.string("heliostat_id")
            _check(bool(hid), file, entry.field("heliostat_id"), "empty")
            dt = _check_datetime(file, entry.field("datetime"), entry.get("datetime"))
            _add_entry(out, ambiguous, int(key), TimestampEntry(hid, dt), file, key)
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
        items = {int(k): v for k, v in entries.items()}  # pyright: ignore[reportArgumentType]
    else:
        items = {r.record_id: TimestampEntry(r.heliostat_id, r.datetime) for r in entries if r.datetime is not None}
    data = {str(k): {"heliostat_id": items[k].heliostat_id, "datetime": items[k].datetime} for k in sorted(items)}
    _write_json(path, data, indent=1)


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _add_entry(
    out: dict[int, TimestampEntry], ambiguous: set[int], rid: int, entry: TimestampEntry, file: str, where: str
) -> None:
    """Add ``entry`` for record ``rid`` to ``out``; a record listed twice with different
    entries (e.g. ids "7" and "07") is removed and kept in ``ambiguous``, and a DataError
    names it: neither entry is used."""
    if rid in ambiguous or out.get(rid, entry) != entry:
        ambiguous.add(rid)
        out.pop(rid, None)
        raise DataError(file, where, f"record {rid} is listed twice with different entries: neither is used")
    out[rid] = entry


def read_metadata_times(
    path: str | os.PathLike, *, on_error: Callable[[DataError], None] | None = None
) -> dict[int, TimestampEntry]:
    """Read the record times of PAINT's calibration metadata CSV (:data:`METADATA_GLOB`):
    record id -> (heliostat id, UTC datetime as ISO-8601 ``...Z``).

    Args:
        path: the CSV file.
        on_error: None raises the first bad row's :class:`DataError` (field
            ``"row <line>.<column>"``); a callable receives it and the row is skipped.

    Raises:
        DataError: an unreadable file or missing columns (always); bad rows (see ``on_error``).
    """
    file, header, rows = _csv_table(path, METADATA_COLUMNS, METADATA_COLUMNS)
    col = {name: header.index(name) for name in METADATA_COLUMNS}
    out: dict[int, TimestampEntry] = {}
    ambiguous: set[int] = set()
    for line, text_line in rows:
        where = f"row {line}"
        try:
            cells = _csv_cells(file, where, text_line, len(header))
            if cells is None:
                continue
            rid_text, hid, when = (cells[col[c]].strip() for c in METADATA_COLUMNS)
            if not _ID_RE.match(rid_text):
                raise DataError(file, f"{where}.Id", f"record id is not numeric: {rid_text[:40]!r}")
            _check(bool(hid), file, f"{where}.HeliostatId", "empty")
            _check_datetime(file, f"{where}.DateTime", when)
            iso = utc_datetime(when).strftime("%Y-%m-%dT%H:%M:%S.%fZ").replace(".000000Z", "Z")
            _add_entry(out, ambiguous, int(rid_text), TimestampEntry(hid, iso), file, where)
        except DataError as e:
            if on_error is None:
                raise
            on_error(e)
    return out
