"""``calibration-timestamps.json``: record id -> heliostat id and UTC time."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping

from .._errors import DataError
from ._common import _ID_RE, CalibrationRecord, TimestampEntry, _check, _check_datetime, _load_json, _Node, _write_json

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
            rid = int(key)
            if rid in ambiguous or out.get(rid, TimestampEntry(hid, dt)) != TimestampEntry(hid, dt):
                ambiguous.add(rid)
                out.pop(rid, None)
                raise DataError(file, key, f"record {rid} is listed twice with different entries: neither is used")
            out[rid] = TimestampEntry(hid, dt)
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
