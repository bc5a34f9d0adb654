"""Download PAINT data from a STAC catalogue into PAINT's folder layout.
PAINT publishes its data as a static STAC catalogue (root
``https://paint-database.org/WRI1030197/WRI1030197-catalog-stac.json``)::

    WRI1030197-catalog                       root catalogue
    ├── WRI1030197-tower-measurements        item, asset "measurements"
    ├── weather-collection                   (ignored here)
    └── <H>-heliostat-catalog                one catalogue per heliostat
        ├── <H>-heliostat-properties-collection -> item -> asset (properties JSON)
        ├── <H>-calibration-collection          -> items "<ID>" -> assets
        │     calibration_properties, flux_image, flux_centered_image,
        │     cropped_image, raw_image
        └── <H>-deflectometry-collection        -> items -> assets
              raw_measurement, filled_measurement, results_summary

:func:`fetch_catalog` walks such a catalogue (from an ``http(s)://`` URL, a
``file://`` URL or a local path) with pystac and writes what PAINT's own client
writes::

    <out>/WRI1030197-tower-measurements.json
    <out>/<H>/Properties/<H>-heliostat-properties.json
    <out>/<H>/Calibration/<ID>-calibration-properties.json   (+ <ID>-flux.png, ...)
    <out>/<H>/Deflectometry/<H>-...-deflectometry.h5

The file name is the last path segment of the asset's href (PAINT's rule), the
heliostat folder the part of the heliostat catalogue id before the first ``-``.

Safety. A catalogue is untrusted input; :class:`~heliojax._errors.DataError` is
raised, before anything is written (every file is planned before the first is
fetched), for

- a destination file name that is empty, hidden, or carries a path separator
  (also percent-encoded) or other odd characters, and a heliostat id that is not
  a plain name;
- a destination path whose folders (below the output folder) or file are
  symbolic links;
- an asset href or a catalogue link (child/item) whose relative href climbs out
  of the root catalogue's folder (``..`` segments, also percent-encoded, e.g.
  ``../../../../evil.json``; one that stays inside, ``../shared/x.json``, is
  fetched), and an absolute URL with a ``..`` path segment;
- a local file (absolute path or ``file://``) outside the root catalogue's
  folder (symbolic links resolved) or, for a remote catalogue, any local file;
- an href with a scheme other than ``http``, ``https`` or ``file``.

Absolute ``http(s)`` hrefs are accepted (PAINT's catalogue uses them throughout).

Resume and verification. Every file is streamed to a hidden temporary file
(``.<name>.<random>.part``) in its destination folder, checked, and renamed onto
its name: an interrupted download never looks complete. Checked are the size
and checksum from the STAC ``file`` extension (``file:size``, ``file:checksum``,
a multihash) when the asset has them, that a ``.json`` file parses, and that a
``.png`` or ``.h5`` file starts with its format's signature (not an HTML error page). Each
completed file is appended to the journal ``<out>/.heliojax-fetch.jsonl``
(path, source href, size, SHA-256). With ``resume=True`` a file that already
exists is skipped when it matches the asset's ``file:size``/``file:checksum``, or,
without those, its journal record (same source, size and SHA-256); otherwise it
is downloaded again. PAINT's catalogue has no ``file`` extension, so the journal
is what makes a resumed PAINT download trustworthy. One fetch per output folder
at a time: a run deletes stale ``.part`` files of the files it plans.

Network. ``http(s)`` is streamed with :mod:`requests`; urllib3's ``Retry`` retries
connection errors and the answers 408, 429, 500, 502, 503, 504, not others (404, ...)
nor a broken-off body, after 0, 1, 2, 4, ... s (a server's Retry-After is not
followed: it may ask for hours). A STAC JSON file is read to at most ``MAX_STAC_BYTES``
(64 MiB) whatever its Content-Length says (a UTF-8 byte-order mark is allowed), an asset
to at most its ``file:size``, else ``MAX_ASSET_BYTES`` (4 GiB; a ``.json`` asset
``MAX_STAC_BYTES``): a body without end is broken off before it fills the disk. Local paths and ``file://`` URLs are
read with :func:`open`. A compressed (``Content-Encoding``) body that inflates to more
than ``MAX_INFLATION`` (100) times the bytes received, beyond its first 16 MiB, is broken
off (a gzip bomb), as is a body slower than ``MIN_BYTES_PER_S`` (1 KiB/s) on average once
the timeout has passed (a server that drips a byte within each read timeout). An HTTP
redirect is followed only to http or https, never from https down to http, and with
``same_host_only`` only on the same host; one refused (the root is a :class:`DataError`,
an asset a failed file) names the URL and the target.

Errors. Unsafe hrefs and an unreadable root raise :class:`DataError` naming the
href; a STAC file below the root that cannot be read (network error after retries,
broken JSON) and an asset that fails to download or verify are listed in
:attr:`FetchReport.failed` and the run goes on; running it again retries them."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import datetime as dt
import functools
import hashlib
import os
import re
import tempfile
import urllib.parse
from collections.abc import Callable, Sequence
from pathlib import Path, PurePosixPath

import pystac

from .._errors import DataError
from .._io import shown_value
from .._sun import utc_datetime
from ._common import TOWER_FILE_SUFFIX, TimestampEntry, requested_heliostats
from ._stac_io import (
    _COLLECTION_SUFFIX,
    _FOLDER,
    _HELIOSTAT_SUFFIX,
    _HREF_HELIOSTAT_RE,
    _MULTIHASH,
    _NAME_RE,
    _TOWER_SUFFIX,
    CALIBRATION_ASSETS,
    COLLECTIONS,
    HREF_PROBLEM,
    JOURNAL_NAME,
    FetchReport,
    RedirectRefused,
    Transport,
    _Checker,
    _content_ok,
    _dest_name,
    _Failure,
    _hash_file,
    _heliostat_id,
    _is_url,
    _Journal,
    _most_bytes,
    _parse_multihash,
    _Reader,
    _safe_dest,
    _scheme,
    _Scope,
    _short,
    _Task,
    read_failure,
)
from ._timestamps import read_timestamps, write_timestamps


def _why(e: DataError) -> str:
    """The reason of an unreadable STAC file, with its field where one is named."""
    return e.reason if e.field is None else f"field '{e.field}': {e.reason}"


def _item_time(item: pystac.Item) -> dt.datetime | None:
    """The item's ``datetime`` (else ``start_datetime``); one without a time zone is UTC."""
    when = item.datetime if item.datetime is not None else item.common_metadata.start_datetime
    return None if when is None else utc_datetime(when)  # naive: UTC (PAINT's convention), not local time


def _as_utc(t: dt.datetime | dt.date | None, end: bool) -> dt.datetime | None:
    if t is None:
        return None
    if not isinstance(t, dt.datetime):
        t = dt.datetime.combine(t, dt.time.max if end else dt.time.min)
    return utc_datetime(t)


def _links(obj: pystac.STACObject, *rels: str) -> list[str]:
    out = []
    for link in obj.links:
        if link.rel in rels and isinstance(link.target, str):
            out.append(link.target)
    return out


def fetch_catalog(
    source: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    heliostats: Sequence[str] | None = None,
    collections: Sequence[str] = ("properties", "calibration"),
    calibration_assets: Sequence[str] = ("calibration_properties",),
    start: dt.datetime | dt.date | None = None,
    end: dt.datetime | dt.date | None = None,
    max_items: int | None = None,
    resume: bool = True,
    include_tower: bool = True,
    workers: int = 8,
    timeout_s: float = 60.0,
    retries: int = 2,
    progress: Callable[[str], None] | None = None,
    transport: Transport | None = None,
    same_host_only: bool = False,
) -> FetchReport:
    """Download a PAINT-style STAC catalogue's assets into PAINT's layout.

    Args:
        source: root catalogue: ``http(s)://`` or ``file://`` URL, local path of its
            JSON file, or a folder holding ``catalog.json`` / ``*-catalog-stac.json``.
        out_dir: output folder (created).
        heliostats: heliostat ids to fetch (a list, or one id as a string; default: every
            heliostat catalogue).
        collections: any of :data:`COLLECTIONS`.
        calibration_assets: asset keys of calibration items to fetch (any of
            :data:`CALIBRATION_ASSETS`); other collections' items are fetched whole.
        start, end: keep calibration and deflectometry items whose ``datetime``
            (or ``start_datetime``) lies in ``[start, end]``; naive values are UTC,
            a plain date as ``end`` means the end of that day. Properties items are
            never filtered by date (the calibration needs them).
        max_items: at most this many calibration (and deflectometry) items per
            heliostat, the earliest first (after the date filter).
        resume: skip files already complete (see the module docstring); False
            downloads everything again.
        include_tower: fetch the tower-measurements file linked from the root.
        workers: threads reading STAC items and downloading assets.
        timeout_s, retries: per request: seconds to connect and between received bytes; retries of
            connection errors and answers 408, 429, 500, 502, 503, 504 (see the module docstring).
        progress: called with one line of text per step (the CLI prints to stderr).
        transport: replaces the reading of hrefs, see :data:`Transport` (tests inject failures through it).
        same_host_only: refuse an HTTP redirect to another host (default: followed, as a
            CDN or a moved site needs; see "Network").

    Returns:
        :class:`FetchReport`. Download failures are reported there, not raised.

    Raises:
        DataError: unreadable root catalogue, or an unsafe href (see the module
            docstring). Unreadable STAC files below the root are reported in
            :attr:`FetchReport.failed` instead.
        ValueError: unknown collection or calibration asset key.
    """
    unknown = set(collections) - set(COLLECTIONS)
    if unknown:
        raise ValueError(f"unknown collection(s) {sorted(unknown)}; choose from {', '.join(COLLECTIONS)}")
    unknown = set(calibration_assets) - set(CALIBRATION_ASSETS)
    if unknown:
        raise ValueError(f"unknown calibration asset(s) {sorted(unknown)}; choose from {', '.join(CALIBRATION_ASSETS)}")
    if max_items is not None and max_items < 1:
        raise ValueError(f"max_items must be >= 1, got {max_items}")
    t0, t1 = _as_utc(start, False), _as_utc(end, True)
    if t0 is not None and t1 is not None and t0 > t1:
        raise ValueError(f"start {t0} is after end {t1}")
    say = progress or (lambda _msg: None)

    root_href = _root_href(source)
    scope = _Scope.of(root_href)
    out = Path(out_dir)
    wanted = (
        None
        if heliostats is None
        else {h.strip() for h in requested_heliostats(heliostats, "fetch_catalog") if h.strip()}
    )
    warnings: list[str] = []
    all_tasks_done: dict[str, list] = {"downloaded": [], "skipped": [], "failed": []}
    timestamps: dict[int, TimestampEntry] = {}  # record id -> (heliostat, item datetime)
    nbytes = [0]

    reader = _Reader(transport, timeout_s, retries, connections=workers, same_host_only=same_host_only)
    with (
        contextlib.ExitStack() as stack,
        contextlib.closing(reader),
        cf.ThreadPoolExecutor(max_workers=max(1, workers)) as pool,
        _stopped_on_error(pool, reader),
    ):
        root = reader.stac(root_href)  # before the output folder is made: a bad root leaves nothing behind
        stack.enter_context(_made_folder(out))
        out = out.resolve()
        journal = _Journal(out)
        if (out / TIMESTAMPS_FILE).is_dir():  # found now, not after the downloads
            raise DataError(out / TIMESTAMPS_FILE, None, "is a folder: the record times cannot be written")
        say(f"catalogue {root.id} ({root_href})")
        child_hrefs = []
        tower_hrefs = []
        for field, raw in [("links.child", r) for r in _links(root, "child")] + [
            ("links.item", r) for r in _links(root, "item")
        ]:
            href = scope.resolve(raw, root_href, root_href, field)
            m = _HREF_HELIOSTAT_RE.search(raw)
            if m:
                if wanted is not None and m.group(1) not in wanted:
                    continue
                child_hrefs.append(href)
            elif "tower-measurements" in raw:
                if include_tower:
                    tower_hrefs.append(href)
            elif "weather" in raw:
                continue
            else:
                child_hrefs.append(href)  # unknown naming: read it and look at its id

        child_hrefs = list(dict.fromkeys(child_hrefs))  # a child linked many times is read once
        say(f"reading {len(child_hrefs)} child catalogue(s) of the root")
        children = list(pool.map(reader.stac_or_error, child_hrefs))
        catalogs: dict[str, tuple[pystac.STACObject, str]] = {}
        for obj, href in zip(children, child_hrefs, strict=True):
            if isinstance(obj, DataError):
                all_tasks_done["failed"].append((href, _why(obj)))
                say(f"  FAILED {href}: {_why(obj)}")
                continue
            if isinstance(obj, pystac.Item) and obj.id.endswith(_TOWER_SUFFIX):
                if include_tower:
                    tower_hrefs.append(href)
                continue
            if not obj.id.endswith(_HELIOSTAT_SUFFIX):
                continue  # weather collection or something else
            hid = _heliostat_id(obj.id, href)
            if wanted is not None and hid not in wanted:
                continue
            if hid in catalogs:
                first = catalogs[hid][1]
                warnings.append(f"two heliostat catalogues give {hid}: {first} and {href}; the second is ignored")
                continue
            catalogs[hid] = (obj, href)
        missing = tuple(sorted(wanted - set(catalogs))) if wanted is not None else ()
        if wanted and not catalogs:  # nothing to fetch: no tower file without its heliostats either
            raise ValueError(f"heliostats: none of {', '.join(missing)} is in the catalogue {source}")
        if not catalogs and wanted is None and not all_tasks_done["failed"]:  # exit 0 with no heliostat said nothing
            raise ValueError(
                f"no heliostat catalogue (<id>-heliostat-catalog) among the {len(child_hrefs)} child(ren) of the "
                f"root of {_short(str(source))}: not a PAINT-style catalogue"
            )
        if missing:
            say(f"not in the catalogue: {', '.join(missing)}")
        say(f"{len(catalogs)} heliostat catalogue(s) selected")

        new_mode = 0o666 & ~_umask()  # read now, in this thread (not at import, not in the workers)

        def run(tasks: list[_Task]) -> tuple[int, int, int]:
            counts = [0, 0, 0]
            futures = [pool.submit(_fetch_one, t, reader, journal, resume, out, new_mode) for t in tasks]
            for t, fut in zip(tasks, futures, strict=True):
                try:
                    status, n = fut.result()
                except _Failure as e:
                    all_tasks_done["failed"].append((t.src, str(e)))
                    counts[2] += 1
                    say(f"  FAILED {t.rel}: {e}")
                    continue
                if status == "downloaded":
                    all_tasks_done["downloaded"].append(t.dest)
                    nbytes[0] += n
                    counts[0] += 1
                else:
                    all_tasks_done["skipped"].append(t.dest)
                    counts[1] += 1
            return counts[0], counts[1], counts[2]

        # Every file is planned before the first is written: an unsafe href anywhere in
        # the catalogue is refused with nothing of it written (not the tower file and the
        # heliostats before the one that has it).
        plans: list[tuple[str, list[_Task]]] = []
        for href in dict.fromkeys(tower_hrefs):  # the tower file
            item = reader.stac_or_error(href)
            if not isinstance(item, DataError | pystac.Item | pystac.Collection):  # a catalogue has no assets
                item = DataError(href, "type", f"expected a STAC item with the tower file, got {type(item).__name__}")
            if isinstance(item, DataError):
                all_tasks_done["failed"].append((href, _why(item)))
                say(f"  FAILED {href}: {_why(item)}")
                continue
            tasks = _plan_assets(scope, out, (), item, lambda _: True, href, warnings, all_tasks_done["failed"])
            plans.append((f"tower {item.id}", tasks))

        plan_heliostat = functools.partial(
            _plan_heliostat, scope=scope, reader=reader, pool=pool, out=out, collections=collections,
            calibration_assets=calibration_assets, t0=t0, t1=t1, max_items=max_items, warnings=warnings,
            failed=all_tasks_done["failed"], timestamps=timestamps,
        )  # fmt: skip
        for k, hid in enumerate(sorted(catalogs), 1):
            cat, cat_href = catalogs[hid]
            tasks = plan_heliostat(hid, cat, cat_href)
            say(f"[{k}/{len(catalogs)}] {hid}: {len(tasks)} file(s) planned")
            plans.append((f"[{k}/{len(catalogs)}] {hid}: {len(tasks)} file(s)", tasks))
        for label, tasks in plans:
            d, s, f = run(tasks)
            say(f"{label}: {d} downloaded, {s} already complete, {f} failed")

    if timestamps:
        _merge_timestamps(out / TIMESTAMPS_FILE, timestamps)
        say(f"{TIMESTAMPS_FILE}: {len(timestamps)} record time(s) from the items' datetimes")
    warnings += _incomplete(out, sorted(catalogs), include_tower, collections, calibration_assets, timestamps)
    report = FetchReport(
        out_dir=out,
        heliostats=tuple(sorted(catalogs)),
        missing=missing,
        downloaded=tuple(all_tasks_done["downloaded"]),
        skipped=tuple(all_tasks_done["skipped"]),
        failed=tuple(all_tasks_done["failed"]),
        warnings=tuple(warnings),
        bytes_downloaded=nbytes[0],
    )
    say(
        f"done: {len(report.downloaded)} downloaded ({report.bytes_downloaded} bytes), "
        f"{len(report.skipped)} already complete, {len(report.failed)} failed"
    )
    return report


@contextlib.contextmanager
def _stopped_on_error(pool: cf.ThreadPoolExecutor, reader: _Reader):
    """On an exception (Ctrl-C, SIGTERM, an unsafe href) the downloads not started are
    cancelled and those under way break off at their next chunk, removing their
    temporary files: the pool's own exit would otherwise wait for every queued file."""
    try:
        yield
    except BaseException:
        reader.stopped.set()
        pool.shutdown(wait=False, cancel_futures=True)
        raise


@contextlib.contextmanager
def _made_folder(folder: Path):
    """Make ``folder`` (and its parents); if the block raises while the folder is new and
    still empty (an error found before the first download), remove it again."""
    made = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    try:
        yield
    except BaseException:
        if made and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
        raise


def _root_href(source: str | os.PathLike) -> str:
    s = os.fspath(source)
    if _is_url(s):
        try:
            scheme = _scheme(s)
            urllib.parse.urlsplit(s).port  # noqa: B018 - raises ValueError for a port out of range
        except ValueError as e:  # "http://[::1": the URL, not a bare "Invalid IPv6 URL"
            raise DataError(s, None, f"not a URL: {e}") from None
        if scheme not in ("http", "https", "file"):
            raise DataError(s, None, f"unsupported scheme {scheme!r} (http, https, file)")
        return s
    p = Path(s)
    if p.is_dir():
        cands = [p / "catalog.json", *sorted(p.glob("*-catalog-stac.json"))]
        found = [c for c in cands if c.is_file()]
        if not found:
            raise DataError(p, None, "folder has no catalog.json or *-catalog-stac.json")
        p = found[0]
    if not p.is_file():
        raise DataError(p, None, "root catalogue not found")
    return str(p.resolve())


class _MalformedAsset(DataError):
    """An asset whose metadata is broken (an empty href, a size or checksum that is not
    one), not hostile: that file fails, the others are fetched. Hostile hrefs (leaving
    the catalogue or the output folder) raise :class:`DataError` and stop the fetch."""


def _plan_assets(
    scope: _Scope,
    out: Path,
    folder: tuple[str, ...],
    item: pystac.Item | pystac.Collection,
    keys: Callable[[str], bool],
    owner: str,
    warnings: list[str],
    failed: list[tuple[str, str]],
) -> list[_Task]:
    """:func:`_plan_asset` of each asset of ``item`` whose key passes ``keys``; one with
    broken metadata goes to ``failed`` (``(owner, reason)``) instead."""
    tasks = []
    for key, asset in item.assets.items():
        if not keys(key):
            continue
        try:
            tasks.append(_plan_asset(scope, out, folder, asset, key, owner, warnings))
        except _MalformedAsset as e:
            failed.append((owner, f"field '{e.field}': {e.reason}; that file is not fetched"))
    return tasks


def _plan_asset(
    scope: _Scope, out: Path, folder: tuple[str, ...], asset: pystac.Asset, key: str, owner: str, warnings: list[str]
) -> _Task:
    field = f"assets.{key}.href"
    raw = asset.href
    problem = asset.extra_fields.get(HREF_PROBLEM)
    if problem is not None:  # missing or not a string in the JSON (see _stac_shape_problem)
        raise _MalformedAsset(owner, field, str(problem))
    if not isinstance(raw, str) or not raw.strip():
        raise _MalformedAsset(owner, field, "empty or non-string href")
    try:
        raw_path = urllib.parse.urlsplit(raw).path if _is_url(raw) else raw
    except ValueError as e:  # "http://[::1": broken, not hostile
        raise _MalformedAsset(owner, field, f"href {_short(raw)} is not a URL: {e}") from None
    if _is_url(raw) and ".." in urllib.parse.unquote(raw_path).replace("\\", "/").split("/"):
        raise DataError(owner, field, f"asset href {_short(raw)} contains a '..' segment (path traversal)")
    src = scope.resolve(raw, owner, owner, field)  # a relative href may climb, within the catalogue's folder
    name = _dest_name(src if _scheme(src) in ("http", "https") else raw, owner, field)  # no ?query, #fragment
    for part in folder:
        if not _NAME_RE.match(part):
            raise DataError(owner, field, f"unsafe folder name {part!r}")
    dest = _safe_dest(out, (*folder, name), owner, field)
    size = asset.extra_fields.get("file:size")
    if size is not None and (not isinstance(size, int) or isinstance(size, bool) or size < 0):
        raise _MalformedAsset(owner, f"assets.{key}.file:size", f"not a non-negative integer: {size!r}")
    checksum = asset.extra_fields.get("file:checksum")
    if checksum is not None:
        try:
            code, _ = _parse_multihash(str(checksum))
        except ValueError as e:
            raise _MalformedAsset(owner, f"assets.{key}.file:checksum", f"not a multihash: {e}") from e
        if code not in _MULTIHASH:
            warnings.append(f"{owner}: asset {key}: multihash code 0x{code:x} unsupported; checksum not verified")
            checksum = None
    return _Task(src, dest, "/".join((*folder, name)), size, checksum, owner)


def _plan_heliostat(
    hid,
    cat,
    cat_href,
    scope,
    reader,
    pool,
    out,
    collections,
    calibration_assets,
    t0,
    t1,
    max_items,
    warnings,
    failed,
    timestamps,
) -> list[_Task]:
    """Plan the downloads of one heliostat; unreadable STAC files go to ``failed``, unsafe hrefs raise."""
    wanted_suffix = {_COLLECTION_SUFFIX[c]: c for c in collections}
    found: dict[str, tuple[pystac.STACObject, str]] = {}
    for raw in _links(cat, "child"):
        if not any(s in raw for s in _COLLECTION_SUFFIX.values()) or any(s in raw for s in wanted_suffix):
            href = scope.resolve(raw, cat_href, cat_href, "links.child")
            obj = reader.stac_or_error(href)
            if isinstance(obj, DataError):
                failed.append((href, _why(obj)))
                continue
            for suffix, name in wanted_suffix.items():
                if obj.id.endswith(suffix):
                    found[name] = (obj, href)
    tasks: list[_Task] = []
    record_items: dict[int, str] = {}  # calibration record id -> the item that gave it
    for name in collections:
        if name not in found:
            warnings.append(f"{hid}: no {name} collection")
            continue
        coll, coll_href = found[name]
        item_hrefs = [scope.resolve(raw, coll_href, coll_href, "links.item") for raw in _links(coll, "item")]
        items = list(pool.map(reader.stac_or_error, item_hrefs))
        selected = []
        for item, href in zip(items, item_hrefs, strict=True):
            if isinstance(item, DataError):
                failed.append((href, _why(item)))
                continue
            if not isinstance(item, pystac.Item):
                raise DataError(href, "type", f"expected a STAC item in {coll.id}, got {type(item).__name__}")
            try:
                when = _item_time(item)
            except ValueError as e:  # a datetime that UTC cannot hold: that item fails, the others are fetched
                failed.append((href, f"field 'properties.datetime': {e}"))
                continue
            if name != "properties" and (t0 is not None or t1 is not None):
                if when is None or (t0 is not None and when < t0) or (t1 is not None and when > t1):
                    continue
            selected.append((when, item.id, item, href))
        if name != "properties":
            far = dt.datetime.max.replace(tzinfo=dt.UTC)
            selected.sort(key=lambda x: (x[0] or far, x[1]))
            if max_items is not None:
                selected = selected[:max_items]
        for when, _, item, href in selected:
            if name == "calibration" and when is not None:
                record_id = _record_id(item)
                if record_id is not None and record_id in record_items:
                    warnings.append(
                        f"{hid}: items {record_items[record_id]} and {href} both give calibration record {record_id}; "
                        f"its time is taken from the first"
                    )
                elif record_id is not None:
                    record_items[record_id] = href
                    utc = when.astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
                    timestamps[record_id] = TimestampEntry(hid, utc)
            wanted = (lambda key: key in calibration_assets) if name == "calibration" else (lambda _: True)
            tasks += _plan_assets(scope, out, (hid, _FOLDER[name]), item, wanted, href, warnings, failed)
    seen: dict[Path, _Task] = {}
    for t in tasks:
        if t.dest in seen and seen[t.dest].src != t.src:
            raise DataError(t.where, None, f"two assets map onto {t.rel}: {seen[t.dest].src} and {t.src}")
        seen[t.dest] = t
    return list(seen.values())


def _incomplete(
    out: Path,
    heliostats: Sequence[str],
    include_tower: bool,
    collections: Sequence[str],
    calibration_assets: Sequence[str],
    timestamps: dict[int, TimestampEntry],
) -> list[str]:
    """What the folder lacks for ``heliojax calibrate`` although every download that
    was planned succeeded (the catalogue does not hold it): a tower file, a fetched
    heliostat's properties file, the calibration file of a record whose time was
    written."""
    lacking = []
    if include_tower and not any(out.glob(f"*{TOWER_FILE_SUFFIX}")):
        lacking.append(f"no tower file (*{TOWER_FILE_SUFFIX}): the catalogue links none; calibrate needs one")
    for hid in heliostats if "properties" in collections else ():
        if (out / hid / "Calibration").is_dir() and not any((out / hid / "Properties").glob("*.json")):
            lacking.append(f"{hid}: calibration records but no properties file (none in the catalogue): not loadable")
    if "calibration_properties" in calibration_assets:
        missing = sorted(
            rid
            for rid, entry in timestamps.items()
            if not (out / entry.heliostat_id / "Calibration" / f"{rid}-calibration-properties.json").is_file()
        )
        if missing:
            lacking.append(
                f"{len(missing)} calibration record(s) with a time but no calibration-properties file (e.g. record "
                f"{missing[0]} of {timestamps[missing[0]].heliostat_id}): the item has no such asset, or it failed"
            )
    return lacking


TIMESTAMPS_FILE = "calibration-timestamps.json"
_RECORD_ID_RE = re.compile(r"(?<![0-9])([0-9]{1,18})-calibration-properties\.json$")
_ITEM_ID_RE = re.compile(r"[0-9]{1,18}")  # ASCII digits that fit an int64 (not "²", not 5000 digits)


def _record_id(item: pystac.Item) -> int | None:
    """The calibration record id of ``item``: from its calibration-properties asset's
    file name (PAINT's ``<ID>-calibration-properties.json``), else an all-digit item id."""
    asset = item.assets.get("calibration_properties")
    try:
        m = _RECORD_ID_RE.search(urllib.parse.urlparse(asset.href).path) if asset is not None else None
    except ValueError:  # an href that is no URL fails when its asset is planned
        m = None
    if m:
        return int(m.group(1))
    return int(item.id) if _ITEM_ID_RE.fullmatch(item.id) else None


def _merge_timestamps(path: Path, new: dict[int, TimestampEntry]) -> None:
    """Add ``new`` to ``path`` (PAINT's calibration-timestamps.json), keeping the
    entries of earlier downloads; an unreadable old file is replaced."""
    old: dict[int, TimestampEntry] = {}
    if path.exists():
        with contextlib.suppress(DataError):
            old = read_timestamps(path, on_error=lambda _e: None)
    write_timestamps(path, {**old, **new})


def _fetch_one(
    task: _Task, reader: _Reader, journal: _Journal, resume: bool, out: Path, new_mode: int
) -> tuple[str, int]:
    """Download ``task`` (or skip it, complete already); the file gets the mode of the
    file it replaces, else ``new_mode`` (``0o666`` less the umask): the rule of
    :func:`heliojax._io._publish` for every other output."""
    checker = _Checker(task)
    dest = task.dest
    if dest.is_symlink():
        raise _Failure(f"{dest} is a symbolic link")
    if dest.parent.is_dir():  # leftovers of an interrupted run (one fetch per output folder at a time)
        for stale in dest.parent.glob(f".{_glob_escape(dest.name)}.*.part"):
            with contextlib.suppress(OSError):
                stale.unlink()
    if resume and dest.is_file():
        algos = [hashlib.sha256] + ([checker.algo] if checker.algo else [])
        hs = _hash_file(dest, algos)
        size = dest.stat().st_size
        if checker.has_reference:
            if checker.check(size, hs[-1]) is None and _content_ok(dest) is None:
                return "skipped", 0
        else:
            rec = journal.records.get(task.rel)
            if (
                rec is not None
                and rec.get("href") == task.src
                and rec.get("size") == size
                and rec.get("sha256") == hs[0].hexdigest()
                and _content_ok(dest) is None
            ):
                return "skipped", 0
    dest.parent.mkdir(parents=True, exist_ok=True)
    if dest.parent.resolve() != dest.parent or not str(dest.parent).startswith(str(out)):
        raise _Failure(f"{dest.parent} resolves outside the output folder")
    fd, tmp_name = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".part")
    tmp = Path(tmp_name)
    try:
        sha = hashlib.sha256()
        other = checker.algo() if checker.algo else None
        size = 0
        most = _most_bytes(task.size, dest.name)
        try:
            with os.fdopen(fd, "wb") as f:
                with reader.chunks(task.src) as chunks:
                    for chunk in chunks:
                        if reader.stopped.is_set():
                            raise _Failure("stopped: the run was interrupted")
                        if size + len(chunk) > most:
                            said = "the catalogue's file:size" if task.size is not None else "the most accepted"
                            raise _Failure(f"more than {most} bytes ({said}): download broken off")
                        f.write(chunk)
                        sha.update(chunk)
                        if other is not None:
                            other.update(chunk)
                        size += len(chunk)
                f.flush()
                os.fsync(f.fileno())
        except RedirectRefused as e:  # the failure is listed with the href: not named twice
            raise _Failure(f"download failed: {e.reason if e.source == task.src else e}") from None
        except OSError as e:
            raise _Failure(f"download failed: {read_failure(e)}") from e
        problem = checker.check(size, other if other is not None else sha) or _content_ok(tmp, dest.name)
        if problem:
            raise _Failure(problem)
        os.chmod(tmp, _replaced_mode(dest, new_mode))  # mkstemp creates 0600
        os.replace(tmp, dest)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    journal.add(task.rel, task.src, size, sha.hexdigest())
    return "downloaded", size


def _umask() -> int:
    """The process umask, read without changing it where /proc allows."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _replaced_mode(dest: Path, new_mode: int) -> int:
    """The mode a plain ``open(dest, "w")`` leaves: that of the file ``dest`` replaces (a
    download of a changed file, or ``--no-resume``: the umask of the import was given
    instead), else ``new_mode``."""
    try:
        return dest.stat().st_mode & 0o7777
    except FileNotFoundError:
        return new_mode


def _glob_escape(name: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", name)


def _journal_path_problem(out: Path, rel: str) -> str | None:
    """Why the journal's ``rel`` is not a path fetch writes, inside ``out`` (an absolute
    path, a ``..``, a folder on the way that is a symbolic link), or None."""
    pure = PurePosixPath(rel)
    if pure.is_absolute():
        return "an absolute path, out of the output folder"
    if ".." in pure.parts:
        return "a path out of the output folder ('..')"
    if not rel or "\0" in rel or "\\" in rel or str(pure) != rel:
        return "not a path as fetch writes it (relative, '/' between its parts)"
    folder = out
    for part in pure.parts[:-1]:
        folder = folder / part
        if folder.is_symlink():
            return f"its folder {part!r} is a symbolic link (out of the output folder)"
    return None


def verify_download(out_dir: str | os.PathLike) -> list[str]:
    """Check every file recorded in ``<out_dir>/.heliojax-fetch.jsonl``.

    Returns:
        One message per problem (missing file, symbolic link, size or SHA-256
        differing from the journal, JSON that does not parse, a journal path out of
        ``out_dir``: absolute, with ``..`` or through a linked folder, not read);
        empty when all is well.

    Raises:
        DataError: ``out_dir`` is not a folder, or holds no journal (not a folder
            ``heliojax fetch`` downloaded into: a mistyped path was verified as one
            where all is well).
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise DataError(out, None, "not a folder (missing, or a file): nothing to verify")
    if not ((out / JOURNAL_NAME).exists() or (out / JOURNAL_NAME).is_symlink()):  # a link: _Journal names it
        raise DataError(
            out, JOURNAL_NAME, "missing: not a folder `heliojax fetch` downloaded into (it keeps the journal there)"
        )
    journal = _Journal(out)
    problems = []
    for rel, rec in sorted(journal.records.items()):
        outside = _journal_path_problem(out, rel)
        if outside is not None:  # never read: an edited journal pointed at /etc/shadow, or ../../x
            problems.append(f"{shown_value(rel, 200)}: {outside}; not read")
            continue
        p = out / rel
        if p.is_symlink() or not p.is_file():
            problems.append(f"{rel}: missing or not a regular file")
            continue
        size = p.stat().st_size
        if size != rec.get("size"):
            problems.append(f"{rel}: {size} bytes, the journal says {rec.get('size')}")
            continue
        if _hash_file(p, [hashlib.sha256])[0].hexdigest() != rec.get("sha256"):
            problems.append(f"{rel}: SHA-256 differs from the journal")
            continue
        bad = _content_ok(p)
        if bad:
            problems.append(f"{rel}: {bad}")
    return problems
