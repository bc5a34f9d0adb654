"""The plumbing of :func:`heliojax.paint.fetch_catalog`: reading (requests, retried,
bounded), checksums, the resume journal, and the safety checks on catalogue hrefs."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import os
import re
import threading
import time
import urllib.parse
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pystac
import requests
import urllib3
from requests.adapters import HTTPAdapter
from urllib3.exceptions import MaxRetryError
from urllib3.util import Retry

from .._errors import DataError

COLLECTIONS: tuple[str, ...] = ("properties", "calibration", "deflectometry")
"""Collections of a heliostat catalogue that :func:`fetch_catalog` can download."""

CALIBRATION_ASSETS: tuple[str, ...] = (
    "calibration_properties",
    "flux_image",
    "flux_centered_image",
    "cropped_image",
    "raw_image",
)
"""Asset keys of PAINT's calibration items."""

JOURNAL_NAME = ".heliojax-fetch.jsonl"

_FOLDER = {"properties": "Properties", "calibration": "Calibration", "deflectometry": "Deflectometry"}
_COLLECTION_SUFFIX = {
    "properties": "-heliostat-properties-collection",
    "calibration": "-calibration-collection",
    "deflectometry": "-deflectometry-collection",
}
_HELIOSTAT_SUFFIX = "-heliostat-catalog"
_TOWER_SUFFIX = "-tower-measurements"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]{0,254}\Z")  # \Z: "$" would let a final newline in
_HELIOSTAT_RE = re.compile(r"^[A-Za-z0-9_]{1,64}\Z")
_HREF_HELIOSTAT_RE = re.compile(r"([A-Za-z0-9_]+)-heliostat-catalog")
_CHUNK = 1 << 20  # bytes per read

# Multihash codes (https://github.com/multiformats/multicodec) -> hashlib constructor.
_MULTIHASH: dict[int, Callable[[], Any]] = {
    0x11: hashlib.sha1,
    0x12: hashlib.sha256,
    0x13: hashlib.sha512,
    0x14: hashlib.sha3_512,
    0x16: hashlib.sha3_256,
    0xD5: hashlib.md5,
    0xB220: lambda: hashlib.blake2b(digest_size=32),
    0xB240: hashlib.blake2b,
}

Transport = Callable[[str, float], io.BufferedIOBase]
"""``open(href, timeout_s) -> binary stream`` (a context manager) that replaces the default
reading (:mod:`requests` for ``http(s)`` URLs, :func:`open` for local paths); it raises
:class:`OSError`, and its ``TimeoutError`` and ``ConnectionError`` are retried."""


# --------------------------------------------------------------------------- results
@dataclasses.dataclass(frozen=True)
class FetchReport:
    """What :func:`fetch_catalog` did.

    Attributes:
        out_dir: the output folder.
        heliostats: ids of the heliostats visited, sorted.
        missing: requested heliostat ids that the catalogue does not have.
        downloaded: files written in this run.
        skipped: files already complete (resume), not downloaded again.
        failed: ``(href, reason)`` of every asset that could not be fetched or
            failed verification; its destination file was not written.
        warnings: notes (unsupported checksum algorithm, heliostat without a
            wanted collection, ...).
        bytes_downloaded: bytes written in this run.
    """

    out_dir: Path
    heliostats: tuple[str, ...]
    missing: tuple[str, ...]
    downloaded: tuple[Path, ...]
    skipped: tuple[Path, ...]
    failed: tuple[tuple[str, str], ...]
    warnings: tuple[str, ...]
    bytes_downloaded: int

    @property
    def ok(self) -> bool:
        """True when nothing failed and every requested heliostat was found."""
        return not self.failed and not self.missing


@dataclasses.dataclass(frozen=True)
class _Task:
    src: str
    dest: Path
    rel: str
    size: int | None
    checksum: str | None  # multihash hex
    where: str  # STAC file that named the asset, for messages


class _Failure(Exception):
    pass


# --------------------------------------------------------------------------- hrefs
def _short(text: str, most: int = 120) -> str:
    """``repr(text)`` for a message, at most ``most`` characters of it (a catalogue's href
    of 5000 characters made an error line of 10 kB)."""
    return repr(text) if len(text) <= most else f"{text[: most // 2]!r}...{text[-most // 2 :]!r}"


def read_failure(e: OSError) -> str:
    """A one-line reason of a failed read or download, for a message: the innermost cause
    of requests' and urllib3's wrappers (a ``ConnectionError(MaxRetryError(...
    NameResolutionError(...)))`` repr of 400 characters had been the message), with a
    hint where the server could not be reached at all."""
    inner: BaseException = e
    seen: set[int] = set()
    while id(inner) not in seen:  # requests wraps urllib3's MaxRetryError, which holds its reason
        seen.add(id(inner))
        nxt = getattr(inner, "reason", None)
        if not isinstance(nxt, BaseException) and inner.args and isinstance(inner.args[0], BaseException):
            nxt = inner.args[0]
        if not isinstance(nxt, BaseException):
            break
        inner = nxt
    text = str(inner) or type(inner).__name__
    text = re.sub(r"^\w*Connection(Pool)?\(host='[^']*', port=\d+\): ", "", text)  # said by the href already
    if isinstance(inner, (urllib3.exceptions.NameResolutionError, urllib3.exceptions.NewConnectionError)):
        return f"cannot reach the server ({_short(text, 160)[1:-1]}): no network connection, or a proxy needed?"
    return f"{type(inner).__name__}: {_short(text, 200)[1:-1]}"


def _is_url(href: str) -> bool:
    return bool(re.match(r"^[A-Za-z][A-Za-z0-9+.-]*://", href))


def _scheme(href: str) -> str:
    return urllib.parse.urlsplit(href).scheme.lower() if _is_url(href) else ""


def _local_path(href: str) -> str:
    if _scheme(href) == "file":
        return urllib.parse.unquote(urllib.parse.urlsplit(href).path)
    return href


def _resolve(raw: str, owner: str) -> str:
    """Absolute href of ``raw`` as written in the STAC file whose absolute href is ``owner``."""
    if _is_url(raw):
        return raw
    if _scheme(owner) in ("http", "https"):
        return urllib.parse.urljoin(owner, raw)
    if os.path.isabs(raw):
        return os.path.normpath(raw)
    # a relative href is a URI reference: %2D is "-" on disk too, as a web server reads it (and as the file is named)
    return os.path.normpath(os.path.join(os.path.dirname(_local_path(owner)), urllib.parse.unquote(raw)))


@dataclasses.dataclass(frozen=True)
class _Scope:
    """Where hrefs of a catalogue may point (see the module docstring)."""

    remote: bool
    base: str  # URL prefix ending in "/" (remote) or real path of the root's folder (local)

    @classmethod
    def of(cls, root_href: str) -> _Scope:
        if _scheme(root_href) in ("http", "https"):
            parts = urllib.parse.urlsplit(root_href)
            path = parts.path.rsplit("/", 1)[0] + "/"
            return cls(True, urllib.parse.urlunsplit((parts.scheme, parts.netloc, path, "", "")))
        return cls(False, os.path.realpath(os.path.dirname(_local_path(root_href))))

    def _inside_local(self, path: str) -> bool:
        real = os.path.realpath(path)
        return os.path.commonpath([real, self.base]) == self.base

    def resolve(self, raw: str, owner: str, where: str, field: str) -> str:
        """Resolve ``raw`` against ``owner`` and check it; raise :class:`DataError` if unsafe."""
        if not isinstance(raw, str) or not raw:
            raise DataError(where, field, "empty or non-string href")
        if "\x00" in raw:
            raise DataError(where, field, f"href {_short(raw)} contains a NUL character")
        try:
            href = _resolve(raw, owner)
            scheme = _scheme(href)
            urllib.parse.urlsplit(href).port  # noqa: B018 - raises ValueError for a port out of range
        except ValueError as e:  # "http://[::1": the href, not a bare "Invalid IPv6 URL"
            raise DataError(where, field, f"href {_short(raw)} is not a URL: {e}") from None
        relative = not _is_url(raw) and not os.path.isabs(raw)
        if scheme in ("http", "https"):
            if relative and self.remote and not href.startswith(self.base):
                raise DataError(where, field, f"relative href {_short(raw)} leaves the catalogue folder {self.base}")
            return href
        if scheme not in ("", "file"):
            raise DataError(where, field, f"href {_short(raw)}: scheme {scheme!r} is not supported (http, https, file)")
        if self.remote:
            raise DataError(where, field, f"href {_short(raw)}: a remote catalogue may not point at local files")
        if not self._inside_local(_local_path(href)):
            kind = "relative href" if relative else "absolute path"
            raise DataError(
                where, field, f"{kind} {_short(raw)} points outside the catalogue folder {self.base} (path traversal)"
            )
        return href


# --------------------------------------------------------------------------- I/O
_RETRY_STATUSES = (408, 429, 500, 502, 503, 504)
_BACKOFF_FACTOR_S = 0.5  # urllib3's Retry: the first retry at once, retry k >= 2 after 0.5 * 2**(k - 1) s


class RedirectRefused(requests.RequestException):
    """An HTTP redirect not followed: to another host (unless allowed) or to a scheme
    other than http/https. ``source``: the URL that redirected; ``reason``: the message
    without it."""

    def __init__(self, source: str, reason: str, response: requests.Response):
        super().__init__(f"{source} {reason}", response=response)
        self.source, self.reason = source, reason


def _redirect_hook(same_host_only: bool) -> Callable[..., Any]:
    """A requests response hook that refuses, before it is followed, a redirect to a
    scheme other than http/https, from https to plain http (a downgrade), or, with
    ``same_host_only``, to another host."""

    def check(response: requests.Response, *args, **kwargs) -> requests.Response:
        if not response.is_redirect:
            return response
        source = str(response.url)
        location = response.headers.get("location", "")
        try:
            target = urllib.parse.urljoin(source, location)
            src, dst = urllib.parse.urlsplit(source), urllib.parse.urlsplit(target)
            dst.port  # noqa: B018 - raises ValueError for a port out of range
        except ValueError as e:  # "http://[::1": not a URL
            response.close()
            reason = f"redirects to {location[:200]!r}, not a URL ({e}): not followed"
            raise RedirectRefused(source, reason, response) from None
        problem = None
        if dst.scheme not in ("http", "https"):
            problem = f"redirects to {target}: only http and https redirects are followed"
        elif src.scheme == "https" and dst.scheme == "http":
            problem = f"redirects from https to plain http, {target}: not followed"
        elif same_host_only and (dst.hostname or "").lower() != (src.hostname or "").lower():
            problem = f"redirects to another host, {target}: not followed (--same-host-only)"
        if problem is not None:
            response.close()
            raise RedirectRefused(source, problem, response)
        return response

    return check


class _Reader:
    """Reads hrefs in chunks (see "Network" in :mod:`._stac`); thread-safe; :meth:`close` closes its session."""

    def __init__(
        self,
        transport: Transport | None,
        timeout_s: float,
        retries: int,
        connections: int,
        same_host_only: bool = False,
    ):
        self.transport, self.timeout_s = transport, timeout_s
        self.retry = Retry(
            total=retries,
            backoff_factor=_BACKOFF_FACTOR_S,
            status_forcelist=_RETRY_STATUSES,
            allowed_methods={"GET"},
            respect_retry_after_header=False,  # a server's Retry-After may ask for hours: back off our way
        )
        self.stopped = threading.Event()  # set when the run stops: downloads under way break off
        self.session = requests.Session()
        self.session.headers["User-Agent"] = "heliojax-fetch"
        self.session.hooks["response"].append(_redirect_hook(same_host_only))
        adapter = HTTPAdapter(max_retries=self.retry, pool_maxsize=max(1, connections))
        for prefix in ("http://", "https://"):
            self.session.mount(prefix, adapter)

    def close(self) -> None:
        self.session.close()

    @contextlib.contextmanager
    def chunks(self, href: str) -> Iterator[Iterator[bytes]]:
        """The bytes of ``href`` in chunks of at most ``_CHUNK`` bytes, the response or file closed on exit;
        an unreadable href or an HTTP error status (after the retries) raises :class:`OSError`."""
        if self.transport is None and _scheme(href) in ("http", "https"):
            with self.session.get(href, stream=True, timeout=self.timeout_s) as response:
                response.raise_for_status()
                yield _bounded_body(response, self.timeout_s)
        else:
            with self._open(href) as f:
                yield iter(lambda: f.read(_CHUNK), b"")

    def _open(self, href: str):
        """A local file, or the injected transport's stream, its ``TimeoutError`` and ``ConnectionError`` retried."""
        if self.transport is None:
            return open(_local_path(href), "rb")
        retry = self.retry
        while True:
            try:
                return self.transport(href, self.timeout_s)
            except (TimeoutError, ConnectionError) as e:
                try:
                    retry = retry.increment(method="GET", url=href, error=e)
                except MaxRetryError:
                    raise e from None
                retry.sleep()

    def json(self, href: str) -> dict:
        data = bytearray()
        try:
            with self.chunks(href) as chunks:
                for chunk in chunks:
                    data += chunk
                    if len(data) > MAX_STAC_BYTES:  # bounded: a server's Content-Length is not trusted
                        raise DataError(href, None, f"STAC file larger than {MAX_STAC_BYTES} bytes: not read")
        except RedirectRefused as e:
            raise DataError(href, None, e.reason if e.source == href else str(e)) from None
        except OSError as e:
            raise DataError(href, None, f"cannot read STAC file: {read_failure(e)}") from e
        try:
            obj = json.loads(data.decode("utf-8-sig"))  # -sig: a byte-order mark an editor left
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DataError(href, None, f"not a JSON file: {e}") from e
        except (ValueError, RecursionError) as e:  # a number of over 4300 digits, nesting too deep
            raise DataError(href, None, f"not a usable JSON file: {type(e).__name__}: {e}") from None
        if not isinstance(obj, dict):
            raise DataError(href, None, "STAC file is not a JSON object")
        return obj

    def stac_or_error(self, href: str) -> pystac.STACObject | DataError:
        """Like :meth:`stac`, but returns the :class:`DataError` of an unreadable file."""
        try:
            return self.stac(href)
        except DataError as e:
            return e

    def stac(self, href: str) -> pystac.STACObject:
        d = self.json(href)
        problem = _stac_shape_problem(d)
        if problem is not None:  # named by field, not by the exception pystac would raise
            raise DataError(href, *problem)
        try:
            return pystac.read_dict(d, href=href)
        except Exception as e:  # pystac raises several types for malformed STAC
            raise DataError(href, None, f"not a valid STAC object: {e}") from e


_STAC_TIMES = ("datetime", "start_datetime", "end_datetime")


def _json_text(value: object) -> str:
    """A JSON value for a message, cut (:func:`_short`) without repr's quotes."""
    text = json.dumps(value)
    return text if len(text) <= 120 else f"{text[:60]}...{text[-60:]}"


HREF_PROBLEM = "heliojax:href_problem"
"""Key put into an asset of a STAC JSON object whose ``href`` is missing or not a string
(the href becomes ``""``): that asset fails when it is planned, the item's others are
fetched."""


def _stac_shape_problem(d: dict) -> tuple[str, str] | None:
    """``(field, reason)`` of the first part of a STAC JSON object that is not of the
    shape pystac reads (which would fail with a bare ``KeyError``/``TypeError``):
    ``links`` a list of objects with string ``rel`` and ``href``, ``assets`` an object
    of objects, an item's ``properties`` an object whose
    ``datetime``/``start_datetime``/``end_datetime`` are RFC 3339 strings (or null).
    None when it has that shape. An asset whose ``href`` is missing or not a string
    is marked (:data:`HREF_PROBLEM`) in ``d``."""
    links = d.get("links", [])
    if not isinstance(links, list):
        return "links", f"not a list: {_json_text(links)}"
    for k, link in enumerate(links):
        if not isinstance(link, dict):
            return f"links[{k}]", f"not an object: {_json_text(link)}"
        for key in ("rel", "href"):
            if key not in link:
                return f"links[{k}].{key}", "missing"
            if not isinstance(link[key], str):
                return f"links[{k}].{key}", f"not a string: {_json_text(link[key])}"
    assets = d.get("assets", {})
    if not isinstance(assets, dict):
        return "assets", f"not an object: {_json_text(assets)}"
    for key, asset in assets.items():
        if not isinstance(asset, dict):
            return f"assets.{key}", f"not an object: {_json_text(asset)}"
        if not isinstance(asset.get("href"), str):  # that asset fails alone (see _plan_asset), not the item
            href = asset.pop("href", None)
            asset[HREF_PROBLEM] = "missing" if href is None else f"not a string: {_json_text(href)}"
            asset["href"] = ""
    if d.get("type") != "Feature":
        return None
    properties = d.get("properties")
    if not isinstance(properties, dict):
        return "properties", "missing" if properties is None else f"not an object: {_json_text(properties)}"
    for key in _STAC_TIMES:
        value = properties.get(key)
        if value is None:
            continue
        if not isinstance(value, str):
            return f"properties.{key}", f"not an RFC 3339 string: {_json_text(value)}"
        try:
            pystac.utils.str_to_datetime(value)
        except (ValueError, OverflowError) as e:
            return f"properties.{key}", f"not an RFC 3339 date-time: {_short(value)} ({e})"
    return None


MAX_INFLATION = 100
"""Largest ratio of decoded to received bytes of a compressed (``Content-Encoding``) HTTP
body beyond its first ``_INFLATION_FREE`` bytes: a gzip bomb (a few kB that inflate to
GB) is broken off instead of filling the disk."""
_INFLATION_FREE = 16 * _CHUNK


MIN_BYTES_PER_S = 1024
"""Slowest body accepted once :data:`timeout_s` has passed (a server that drips a byte
now and then, each read within the timeout, would otherwise hold a download forever)."""


def _bounded_body(response: requests.Response, timeout_s: float) -> Iterator[bytes]:
    """``response``'s decoded body in chunks as they arrive; :class:`OSError` once a
    compressed body inflates beyond :data:`MAX_INFLATION` times the bytes received, or
    once, after ``timeout_s``, fewer than :data:`MIN_BYTES_PER_S` per second came in."""
    encoding = response.headers.get("Content-Encoding", "identity").strip().lower()
    decoded = 0
    start = time.monotonic()
    while True:
        try:
            chunk = response.raw.read1(_CHUNK, decode_content=True)  # what arrived: no waiting for a full chunk
        except urllib3.exceptions.HTTPError as e:  # a broken-off body, a read timeout
            raise OSError(f"body broken off: {e}") from e
        if not chunk:
            return
        decoded += len(chunk)
        received = response.raw.tell()  # bytes over the wire, before decoding
        if encoding != "identity" and decoded > _INFLATION_FREE and decoded > MAX_INFLATION * max(received, 1):
            raise OSError(
                f"Content-Encoding {encoding}: {received} bytes received inflate to over {decoded}: "
                "refused as a decompression bomb"
            )
        elapsed = time.monotonic() - start
        if elapsed > timeout_s and received < MIN_BYTES_PER_S * elapsed:
            raise OSError(f"{received} bytes in {elapsed:.0f} s, slower than {MIN_BYTES_PER_S} bytes/s: broken off")
        yield chunk


# --------------------------------------------------------------------------- checksums
def _varint(raw: bytes, pos: int) -> tuple[int, int]:
    """The unsigned varint of ``raw`` at ``pos`` and the position after it."""
    value = shift = 0
    while True:
        if pos >= len(raw):
            raise ValueError("truncated varint")
        b = raw[pos]
        value |= (b & 0x7F) << shift
        pos += 1
        if not b & 0x80:
            return value, pos
        shift += 7


def _parse_multihash(hexstr: str) -> tuple[int, bytes]:
    raw = bytes.fromhex(hexstr)
    code, pos = _varint(raw, 0)
    length, pos = _varint(raw, pos)
    digest = raw[pos:]
    if len(digest) != length:
        raise ValueError(f"digest length {len(digest)} != {length}")
    return code, digest


def _hash_file(path: Path, algos: Iterable[Callable[[], Any]]) -> list[Any]:
    hs = [a() for a in algos]
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(_CHUNK), b""):
            for h in hs:
                h.update(chunk)
    return hs


class _Checker:
    """Expected size/checksum of one asset."""

    def __init__(self, task: _Task):
        self.task = task
        self.algo = None
        self.digest = None
        if task.checksum:
            code, digest = _parse_multihash(task.checksum)  # validated at plan time
            self.algo, self.digest = _MULTIHASH[code], digest

    @property
    def has_reference(self) -> bool:
        return self.task.size is not None or self.digest is not None

    def check(self, size: int, hasher) -> str | None:
        if self.task.size is not None and size != self.task.size:
            return f"size {size} bytes, the catalogue says {self.task.size}"
        if self.digest is not None and hasher.digest() != self.digest:
            return f"checksum mismatch (got {hasher.hexdigest()}, the catalogue says {self.digest.hex()})"
        return None


_SIGNATURES = {".png": (b"\x89PNG\r\n\x1a\n", (0,)), ".h5": (b"\x89HDF\r\n\x1a\n", (0, 512, 1024, 2048))}
"""File signature of a PNG, and of an HDF5 file (at 0 or after a user block), by file name suffix."""


def _content_ok(path: Path, name: str | None = None) -> str | None:
    """Problem with ``path`` judged by ``name`` (default: its own name): a ``.json`` file
    that does not parse, a ``.png`` or ``.h5`` file without its format's signature (an
    HTML error page or an empty body served with status 200)."""
    suffix = os.path.splitext(name or path.name)[1].lower()
    if suffix in _SIGNATURES:
        magic, offsets = _SIGNATURES[suffix]
        with open(path, "rb") as f:
            head = f.read(offsets[-1] + len(magic))
        if not any(head[o : o + len(magic)] == magic for o in offsets):
            return f"downloaded file is not a {suffix[1:].upper()} file (starts with {head[:16]!r})"
        return None
    return _json_ok(path, name)


def _json_ok(path: Path, name: str | None = None) -> str | None:
    """Problem with ``path`` if ``name`` (default: its own name) ends in ``.json`` and it does not parse."""
    if not (name or path.name).lower().endswith(".json"):
        return None
    try:
        with open(path, encoding="utf-8") as f:
            json.load(f)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        return f"downloaded JSON does not parse: {e}"
    except (ValueError, RecursionError) as e:  # a number of over 4300 digits, nesting too deep
        return f"downloaded JSON does not parse: {type(e).__name__}"
    return None


# --------------------------------------------------------------------------- journal
MAX_STAC_BYTES = 64 * 2**20
"""Largest STAC JSON file read (PAINT's largest collection is well below 1 MB), and
largest ``.json`` asset downloaded without a ``file:size``."""

MAX_ASSET_BYTES = 4 * 2**30
"""Largest other asset downloaded without a ``file:size`` (PAINT's largest files, the
deflectometry HDF5 files, are well below); one with a ``file:size`` is broken off once
it exceeds that size. A server that streams without end would otherwise fill the disk."""


def _most_bytes(size: int | None, name: str) -> int:
    """Bytes after which the download of an asset named ``name`` with ``file:size`` ``size`` is broken off."""
    if size is not None:
        return size
    return MAX_STAC_BYTES if name.lower().endswith(".json") else MAX_ASSET_BYTES


class _Journal:
    def __init__(self, out: Path):
        self.path = out / JOURNAL_NAME
        self.lock = threading.Lock()
        self.records: dict[str, dict] = {}
        if self.path.is_symlink():  # appending through it would write outside the output folder
            raise DataError(self.path, None, "the resume journal is a symbolic link; delete it to start over")
        if self.path.exists():
            try:
                with open(self.path, encoding="utf-8", errors="replace") as f:
                    lines = f.readlines()
            except OSError as e:
                raise DataError(
                    self.path, None, f"cannot read the resume journal ({e}); delete it to start over"
                ) from e
            for line in lines:
                try:
                    rec = json.loads(line)
                except (ValueError, RecursionError):  # JSONDecodeError, a number of over 4300 digits, deep nesting
                    continue  # a torn last line of an interrupted run, or damage: that file is fetched again
                if isinstance(rec, dict) and isinstance(rec.get("path"), str):
                    self.records[rec["path"]] = rec

    def add(self, rel: str, href: str, size: int, sha256: str) -> None:
        rec = {"path": rel, "href": href, "size": size, "sha256": sha256}
        line = json.dumps(rec, sort_keys=True) + "\n"
        with self.lock:
            self.records[rel] = rec
            with open(self.path, "a", encoding="utf-8") as f:
                f.write(line)
                f.flush()


# --------------------------------------------------------------------------- destinations
def _dest_name(href: str, where: str, field: str) -> str:
    path = urllib.parse.urlsplit(href).path if _is_url(href) else href
    seg = path.replace("\\", "/").rsplit("/", 1)[-1]
    name = urllib.parse.unquote(seg)
    if not _NAME_RE.match(name) or "/" in name or "\\" in name:
        raise DataError(where, field, f"href {_short(href)} gives the unsafe or empty file name {_short(name)}")
    return name


def _safe_dest(out: Path, parts: Sequence[str], where: str, field: str) -> Path:
    cur = out
    for i, part in enumerate(parts):
        cur = cur / part
        if cur.is_symlink():
            raise DataError(where, field, f"destination {cur} is a symbolic link; refusing to write through it")
        last = i == len(parts) - 1
        if cur.exists() and not (cur.is_file() if last else cur.is_dir()):
            raise DataError(
                where, field, f"destination {cur} exists and is not a regular {'file' if last else 'folder'}"
            )
    return cur


# --------------------------------------------------------------------------- the walk
def _heliostat_id(catalog_id: str, where: str) -> str:
    hid = catalog_id.split("-")[0]
    if not _HELIOSTAT_RE.match(hid):
        raise DataError(where, "id", f"heliostat catalogue id {catalog_id!r} gives an unsafe folder name {hid!r}")
    return hid
