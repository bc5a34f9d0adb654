"""Atomic output: every file heliojax writes goes through :func:`atomic_write` or
:func:`atomic_path`. The file appears under its name only when complete, with the
permissions :func:`open` would give it (``0o666`` less the umask, or the mode of the
file it replaces), not the private ``0o600`` of a temporary file. A destination that
is a symbolic link is written through, as :func:`open` would: the file it points at is
replaced and the link kept (renaming onto the link would replace the link itself). A
destination that is a device (``/dev/null``), a pipe or a socket is refused: renaming
onto it would replace it."""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import secrets
import socket
import stat
import tempfile
import time
import typing
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, no_type_check

MAX_INPUT_BYTES = 2**30
"""An input file larger than this (1 GiB) is refused before it is read: a PAINT file of
the whole plant is tens of MB; a sparse or runaway file of many GB would fill memory."""


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def input_file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be read as an input file, or None: not a regular file (a
    link to /dev/zero is read forever, a FIFO blocks the open), or over
    :data:`MAX_INPUT_BYTES`. OSErrors of the stat (missing, a loop of links) propagate."""
    info = os.stat(path)
    if stat.S_ISDIR(info.st_mode):
        return "a directory, not a file"
    if not stat.S_ISREG(info.st_mode):
        return "not a regular file (a device, pipe or socket)"
    if info.st_size > MAX_INPUT_BYTES:
        return f"{info.st_size} bytes: larger than {MAX_INPUT_BYTES} (1 GiB), not read"
    return None


def check_path_argument(path: object, name: str = "path") -> None:
    """Raise unless ``path``, the argument ``name`` of a reader, names a file or folder:
    a str or :class:`os.PathLike` of a str, not blank. An int was taken for a file
    descriptor (``read_tower(0)`` read standard input, and closed it when done), None
    and a list failed inside ``os.stat`` or ``glob``, bytes inside ``pathlib`` (a
    TypeError naming no argument), and an empty name is the working directory
    (``Path("")`` is ``.``), never what was meant.

    Raises:
        TypeError: not a path (an int, a bool, None, a list, bytes).
        ValueError: an empty or blank path.
    """
    if isinstance(path, bytes) or (isinstance(path, os.PathLike) and isinstance(os.fspath(path), bytes)):
        raise TypeError(f"{name}: expected a str path, got bytes; give os.fsdecode(path)")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{name}: expected a file or folder path (str or os.PathLike), got {type(path).__name__}")
    if not os.fspath(path).strip():
        raise ValueError(f"{name}: empty path (the working directory is not meant; give a name)")


MAX_ID_LENGTH = 255
"""Longest heliostat id (a folder name: most file systems allow 255 bytes)."""

SPREADSHEET_FORMULA_START = ("=", "+", "-", "@")
"""First characters with which a CSV cell is taken for a formula by spreadsheet programs."""


def heliostat_id_problem(text: str) -> str | None:
    """Why ``text`` cannot be a heliostat id, or None: the one rule of the loader (a
    heliostat folder's name), the CLI's options, results.h5 and the CSV inputs.

    PAINT's ids are like ``AA39``; any other name is allowed (another plant's naming)
    that can be written and read back everywhere heliojax writes ids: printable, not
    blank, no white space at either end (read back stripped from a CSV cell or an
    option), no ``,`` (options list ids comma-separated), no path separator, not
    ``.`` or ``..``, at most :data:`MAX_ID_LENGTH` characters, and not starting with a
    character of :data:`SPREADSHEET_FORMULA_START` (written into CSV outputs, such a
    cell is run as a formula by spreadsheet programs)."""
    if not text or not text.strip():
        return "blank"
    if len(text) > MAX_ID_LENGTH:
        return f"longer than {MAX_ID_LENGTH} characters"
    if not text.isprintable():
        return "holds unprintable characters"
    if text != text.strip():
        return "white space at either end"
    if "," in text:
        return "holds a comma (options list names comma-separated)"
    if "/" in text or "\\" in text or text in (".", ".."):
        return "holds a path separator or is . or .. (not a folder name)"
    if text.startswith(SPREADSHEET_FORMULA_START):
        return f"starts with {text[0]!r} (a spreadsheet formula in a CSV cell)"
    return None


def shown_value(value: object, most: int = 60) -> str:
    """``repr(value)`` as shown in a message: at most about ``most`` characters (a file
    or an option may hold a name of 100 kB)."""
    text = repr(value)
    return text if len(text) <= most else f"{text[: most // 2]}...{text[-most // 2 :]} ({len(str(value))} characters)"


_DECIMAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


@no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def is_decimal(text: str) -> bool:
    """Whether ``text`` (blanks around it aside) is a number as a CSV cell writes it: ASCII
    digits, a point, an exponent. Python's float() and int() also take ``1_000``, digits
    of other scripts (``١٢``) and ``infinity``; none is a number in a data file (``1_000``
    read as 1000 joined a row to another record)."""
    return _DECIMAL.fullmatch(text.strip()) is not None


def read_csv_rows(path: str | os.PathLike, what: str) -> tuple[list[str], list[tuple[int, dict[str, str | None]]]]:
    """Header and ``(row number, {column: cell})`` rows of a comma-separated file
    (UTF-8; a spreadsheet's byte-order mark is allowed; blank lines are skipped; a
    row with fewer cells than the header gives ``None`` for the missing ones; every
    cell and column name in Unicode normal form C, so that a letter written decomposed
    is the same text as the letter).

    Args:
        path: the file.
        what: what the file is, for the messages (e.g. ``"an aim-point CSV"``).

    Raises:
        TypeError, ValueError: ``path`` is no path or empty (:func:`check_path_argument`).
        DataError: naming the file (and the column or row): unreadable (not a regular
            file: a FIFO blocked the open), not UTF-8 text, malformed CSV, no header, a
            header separated by ``;`` or tabs, a column listed twice (only its last
            cells would be read), a row with more cells than the header has columns.
    """
    import csv
    import unicodedata

    from ._errors import DataError

    check_path_argument(path)
    try:
        problem = input_file_problem(path)
        if problem is not None:
            raise DataError(path, None, problem)
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            cells = [(reader.line_num, row) for row in reader]
    except OSError as e:
        raise DataError(path, None, f"cannot read: {e.strerror or e}") from None
    except UnicodeDecodeError as e:
        raise DataError(path, None, f"not UTF-8 text (byte {e.start}): not {what}") from None
    except csv.Error as e:
        raise DataError(path, None, f"malformed CSV: {e}") from None
    if not header:
        raise DataError(path, None, f"empty: {what} starts with a header row")
    # one form per text: "\u00c1" and "A\u0301" (the same letter, decomposed, as macOS
    # writes it) are one heliostat id, not two
    header = [unicodedata.normalize("NFC", name.strip()) for name in header]
    if len(header) == 1:
        for sep, name in ((";", "';'"), ("\t", "tabs")):
            if sep in header[0]:
                raise DataError(path, None, f"the header is separated by {name}: {what} is separated by ','")
    twice = sorted({name for name in header if header.count(name) > 1})
    if twice:
        raise DataError(path, twice[0], "column listed twice (only its last cells would be read)")
    rows: list[tuple[int, dict[str, str | None]]] = []
    for line, row in cells:
        if not row:
            continue
        if len(row) > len(header):
            raise DataError(path, f"row {line}", f"more cells than the header has columns: {row[len(header) :]!r}")
        row = [unicodedata.normalize("NFC", cell) for cell in row]
        rows.append((line, dict(zip(header, [*row, *([None] * (len(header) - len(row)))], strict=True))))
    return header, rows


TEMPORARY_MARK = ".heliojax-tmp"
"""In the name of every temporary file heliojax writes (so that stale ones, left by
a killed run, can be recognised and removed: :func:`remove_stale_temporaries`)."""


_OWNER = re.compile(r"\.(?P<host>[A-Za-z0-9_-]+)-(?P<pid>[0-9]+)\.[A-Za-z0-9_]+" + re.escape(TEMPORARY_MARK))
"""The writer's host and process in a temporary's name (:func:`_temporary_prefix`)."""


def _host() -> str:
    """This machine's name as it goes into a temporary's name: its first label, with any
    character but letters, digits, ``-`` and ``_`` replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname().split(".")[0]) or "host"


def _temporary_prefix(name: str) -> str:
    """The start of the name of a temporary beside the output ``name``: hidden, the
    output's name, then the writing host and process (``.summary.json.plant-1234.``),
    so that :func:`remove_stale_temporaries` knows a killed writer's file at once."""
    return f".{name}.{_host()}-{os.getpid()}."


def new_temporary(folder: str | os.PathLike, name: str, suffix: str = "") -> Path:
    """The path of a new temporary in ``folder`` beside the output ``name`` (hidden, the
    writer's host and process in its name: :func:`_temporary_prefix`), not yet made.

    A caller records the path for removal first and then makes the file
    (:func:`make_temporary`): with :func:`tempfile.mkstemp`, a signal (Ctrl-C, a
    ``kill``) between the file's making and its recording left it behind."""
    return Path(folder) / f"{_temporary_prefix(name)}{secrets.token_hex(6)}{TEMPORARY_MARK}{suffix}"


def make_temporary(path: Path) -> None:
    """Make ``path`` (:func:`new_temporary`) empty, readable by its owner only until it
    is published; FileExistsError if it exists."""
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))


def _process_gone(pid: int) -> bool:
    """Whether no process ``pid`` runs on this machine (one of another user runs)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except (OverflowError, OSError):  # PermissionError: another user's process
        return False
    return False


def remove_stale_temporaries(directory: str | os.PathLike, older_than_s: float = 3600.0) -> list[Path]:
    """Remove heliojax's temporary files in ``directory`` that a killed run left
    behind: at once where the name says that this machine wrote it and that process
    has ended (``kill -9``, a power cut), and otherwise once it is older than
    ``older_than_s`` (a file of another machine sharing the folder, or of a process
    whose number was given to another since: a concurrent writer's file is kept).
    Returns the removed paths."""
    removed = []
    now = time.time()
    host = _host()
    for tmp in Path(directory).glob(f".*{TEMPORARY_MARK}*"):
        owner = _OWNER.search(tmp.name)
        dead = owner is not None and owner["host"] == host and _process_gone(int(owner["pid"]))
        with contextlib.suppress(OSError):
            if tmp.is_file() and (dead or now - tmp.stat().st_mtime > older_than_s):
                tmp.unlink()
                removed.append(tmp)
    return removed


def _destination(path: str | os.PathLike) -> Path:
    """``path``, or the file it points at when it is a symbolic link; OSError when that
    exists and is neither a regular file nor a folder (a device such as ``/dev/null``, a
    pipe, a socket: renaming the output onto it would replace it)."""
    path = Path(path)
    path = Path(os.path.realpath(path)) if path.is_symlink() else path
    if path.exists() and not path.is_file() and not path.is_dir():
        raise OSError(errno.EINVAL, "not a regular file (a device, a pipe or a socket): not replaced", str(path))
    return path


def _make_folder(path: Path) -> None:
    """Create the folder of the output ``path``; a file or a dangling link in its place
    (replaced while the run went on) is an OSError naming the output (was "File exists"
    naming the folder)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError as e:
        where = e.filename or path.parent
        raise NotADirectoryError(
            errno.ENOTDIR, f"cannot write it: {where} is a file or a dangling link, not a folder", str(path)
        ) from None


def _umask() -> int:
    mask = os.umask(0o022)  # the only portable way to read it
    os.umask(mask)
    return mask


def _publish(tmp: str | os.PathLike, path: Path) -> None:
    """Give ``tmp`` the mode a plain ``open(path, "w")`` would have, then rename it
    onto ``path``."""
    if path.is_dir():  # name the destination, not the temporary, and never give it a folder's mode
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
    try:
        mode = path.stat().st_mode & 0o7777
    except FileNotFoundError:
        mode = 0o666 & ~_umask()
    os.chmod(tmp, mode)
    os.replace(tmp, path)


_STAGED: dict[str, Path] = {}
"""The temporaries of the :func:`staged_paths` blocks now open (absolute path -> the
output it becomes): :func:`atomic_write` and :func:`atomic_path` write such a path in
place, not through a temporary of their own (a temporary of a temporary,
``..c.X.heliojax-tmp.Y.heliojax-tmp.png``, was left beside the first by a kill)."""
_WRITTEN: set[str] = set()
"""The temporaries of :data:`_STAGED` an atomic writer has written whole."""


@contextlib.contextmanager
def _write_staged(path: Path) -> Iterator[Path]:
    """Yield ``path``, a temporary of :func:`staged_paths`, to write in place; marked
    written once the block completes (a failed write leaves it unpublished, and
    :func:`staged_paths` removes it). An OSError naming no file or the temporary names
    its output instead (a full disk's ENOSPC names no file)."""
    key = os.path.abspath(path)
    _WRITTEN.discard(key)
    try:
        yield path
    except OSError as e:
        if e.filename is None or os.path.abspath(e.filename) == key:
            raise OSError(e.errno, e.strerror or str(e), str(_STAGED[key])) from e
        raise
    _WRITTEN.add(key)


def _staged(path: Path) -> bool:
    """Whether ``path`` is a temporary of a :func:`staged_paths` block now open."""
    return os.path.abspath(path) in _STAGED


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **kwargs) -> Iterator[IO]:
    """Open a temporary file beside ``path``; on success rename it onto ``path``.

    A crash or exception leaves any previous ``path`` untouched and no partial file.
    A ``path`` that is itself a temporary of :func:`staged_paths` is written in place
    (it is renamed when its set is).

    Args:
        path: destination file.
        mode: ``"w"`` (text) or ``"wb"`` (binary).
        **kwargs: passed to :func:`open` (e.g. ``encoding``).
    """
    path = _destination(path)
    if "b" not in mode:
        kwargs.setdefault("encoding", "utf-8")
    if _staged(path):
        with _write_staged(path), open(path, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        return
    _make_folder(path)
    tmp = new_temporary(path.parent, path.name)
    try:
        make_temporary(tmp)
        with open(tmp, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        _publish(tmp, path)
    except OSError as e:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if e.filename is None:  # a write's ENOSPC names no file: name the output, not a temporary
            raise OSError(e.errno, e.strerror or str(e), str(path)) from e
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (for writers that want a file name,
    such as h5py or matplotlib); on success rename it onto ``path``. A ``path`` that is
    itself a temporary of :func:`staged_paths` is yielded as it is."""
    path = _destination(path)
    if _staged(path):
        with _write_staged(path):
            yield path
        return
    _make_folder(path)
    tmp = new_temporary(path.parent, path.stem, path.suffix)
    try:
        make_temporary(tmp)
        yield tmp
        _publish(str(tmp), path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def staged_folder(folder: Path, write: Callable[[Path], Sequence[Path]]) -> list[Path]:
    """``write(tmp)`` fills a temporary folder beside ``folder`` with files (returning
    their paths); once it has returned, they are moved into ``folder`` (made if need be),
    so that a run stopped while writing leaves ``folder``'s previous files as they were.
    Returns the moved files' paths."""
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder.parent, prefix=f".{folder.name}.") as tmp:
        written = write(Path(tmp))
        folder.mkdir(exist_ok=True)
        moved = []
        for p in written:
            target = folder / Path(p).name
            os.replace(p, target)
            moved.append(target)
    return moved


@contextlib.contextmanager
def staged_paths(paths: Sequence[str | os.PathLike | None]) -> Iterator[list[Path | None]]:
    """Temporary paths beside each of ``paths`` (None stays None), to write a set of
    outputs that belong together; when the block completes they are renamed onto their
    destinations one right after the other (:func:`atomic_path` for the set), and
    whatever was not renamed is removed. The block writes each temporary by replacing it
    (heliojax's atomic writers write it in place, as the one temporary of that output;
    another writer replaces it); one left as the empty placeholder is not published.
    A run interrupted while writing (Ctrl-C while the plot is drawn) leaves none of the
    set, not a summary without its results."""
    dests = [None if p is None else _destination(p) for p in paths]
    temps: list[Path | None] = []
    try:
        for d in dests:
            if d is None:
                temps.append(None)
                continue
            _make_folder(d)
            tmp = new_temporary(d.parent, d.stem, d.suffix)
            temps.append(tmp)  # recorded before it is made: removed whenever the block is left
            make_temporary(tmp)
            _STAGED[os.path.abspath(tmp)] = d
        placeholders = {t: os.stat(t).st_ino for t in temps if t is not None}
        yield temps
        for t, d in zip(temps, dests, strict=True):
            # an output the block did not write (still the empty placeholder) is not published
            if t is None or d is None:
                continue
            if os.path.abspath(t) in _WRITTEN or os.stat(t).st_ino != placeholders[t]:
                _publish(str(t), d)
    finally:
        for t in temps:
            if t is not None:
                _STAGED.pop(os.path.abspath(t), None)
                _WRITTEN.discard(os.path.abspath(t))
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(t)


@contextlib.contextmanager
def atomic_h5(path: str | os.PathLike) -> Iterator:
    """An :class:`h5py.File` to fill, built in memory and written to ``path`` with
    :func:`atomic_write` once closed: a disk that fills up is one :class:`OSError`
    naming ``path`` (HDF5 writing to the disk itself spewed an ignored exception per
    buffer and could crash the process), and nothing partial is left."""
    import io

    import h5py

    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as f:
        yield f
    with atomic_write(path, "wb") as out:
        out.write(buffer.getbuffer())


def h5_outside_data(obj: typing.Any, file_name: str) -> str | None:
    """Why the HDF5 object ``obj``, reached in the open file named ``file_name``, holds
    data from outside that file, or None: reached through an external link (to another
    HDF5 file), a dataset stored in external raw files, or a virtual dataset (mapping
    other files). Such a file read data from files it names (another results.h5, any
    file a forger chose) while the messages named only the file given."""
    import h5py

    if obj.file.filename != file_name:
        return f"an external link to {obj.file.filename!r}"
    if isinstance(obj, h5py.Dataset):
        if obj.external:
            return f"a dataset stored in external file(s) {[e[0] for e in obj.external]!r}"
        if obj.is_virtual:
            return "a virtual dataset (it maps data of other files)"
    return None


def h5_first_outside_data(f: typing.Any) -> tuple[str, str] | None:
    """``(HDF5 path, reason)`` of the first link or dataset of the open file ``f`` that
    holds data from outside it (:func:`h5_outside_data`), or None; a soft link is
    followed by its target's own link. Every link of the file is visited (a results.h5
    holds ~60)."""
    import h5py

    hard: list[str] = []

    def check(name: str, link: typing.Any) -> tuple[str, str] | None:
        if isinstance(link, h5py.ExternalLink):
            return name, f"an external link to {link.filename!r} (path {link.path!r})"
        if isinstance(link, h5py.HardLink):
            hard.append(name)  # opened after the visit: HDF5 refuses an object opened inside it
        return None

    found = f.visititems_links(check)
    if found is not None:
        return found
    for name in hard:
        why = h5_outside_data(f[name], f.filename)
        if why is not None:
            return name, why
    return None


H5_OUTSIDE_DATA_REFUSED = "holds data from outside this file ({why}): refused, the file given would not be what is read"


def json_safe(value):
    """``value`` (nested dicts, lists, tuples, numbers) with NaN and infinities as
    ``None`` and numpy scalars as Python numbers: what strict JSON can hold."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, bool | str) or value is None:
        return value
    if hasattr(value, "item") and getattr(value, "shape", None) == ():  # numpy or JAX scalar
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: str | os.PathLike, data) -> None:
    """Write ``data`` as strict, indented JSON, atomically (:func:`atomic_write`);
    non-finite numbers become ``null`` (:func:`json_safe`)."""
    with atomic_write(path) as f:
        json.dump(json_safe(data), f, indent=2, allow_nan=False)
        f.write("\n")
