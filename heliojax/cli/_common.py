"""Shared helpers of the CLI subcommands."""

from __future__ import annotations

import argparse
import collections.abc
import contextlib
import dataclasses
import logging
import math
import os
import re
import sys
import typing
from pathlib import Path

from .._io import shown_value as shown_value  # (the standard library only: the CLI starts fast)

log = logging.getLogger(__name__)


def add_fit_arguments(p) -> None:
    """``--start`` and ``--cache-dir``, shared by the commands that fit."""
    p.add_argument(
        "--start",
        choices=("auto", "nominal"),
        default="auto",
        help="start geometry: per heliostat its own (nominal) actuators, or the fleet-typical ones where its own are "
        "broken (its fit with them twice as noisy or unusable)",
    )
    add_cache_argument(p)


def add_cache_argument(p) -> None:
    """``--cache-dir``: compiled and traced programs kept across runs."""
    p.add_argument(
        "--cache-dir",
        type=path_type,
        default=None,
        help="persistent JAX compilation cache and heliojax's traced programs "
        "(default $HELIOJAX_CACHE_DIR or $XDG_CACHE_HOME/heliojax/jax, ~/.cache/heliojax/jax; 'none' disables)",
    )


def add_data_argument(p) -> None:
    p.add_argument(
        "data_dir",
        nargs="?",
        type=path_type,
        default=None,
        metavar="DATA_DIR",
        help="PAINT-layout directory (default: the embedded real subset of PAINT)",
    )
    p.add_argument(
        "--centroid",
        choices=("utis", "helios"),
        default="utis",
        help="focal-spot centroid: UTIS with HeliOS fallback (default) or HeliOS only",
    )


def load_fleet(args):
    """The fleet of ``args.data_dir`` (default: the embedded subset); says what was
    loaded, and names what was skipped (warnings, shown even with ``--quiet``)."""
    from .._progress import activity
    from ..paint import default_data_dir, load_paint_directory

    path = args.data_dir if args.data_dir is not None else default_data_dir()
    with activity(f"loading {path}", logger=log):
        fleet = load_paint_directory(path, centroid=args.centroid)
    report_load(fleet.report, path)
    return fleet


def option_label(args, dest: str, flag: str) -> str:
    """How a message names option ``dest``: ``flag``, or the config file and key its
    value came from (``--config``; a command line that gives another value wins)."""
    where, value = getattr(args, "config_origin", {}).get(dest, (flag, None))
    return where if where != flag and getattr(args, dest, None) == value else flag


def report_load(report, path) -> None:
    """Say what a load (:class:`heliojax.LoadReport`) of ``path`` loaded, and name what
    it skipped (warnings, shown even with ``--quiet``): every skipped heliostat first,
    then records up to :data:`MAX_LISTED` lines in all; count the suspicious inputs it
    kept (a warning too: a ``--quiet`` run must not hide them)."""
    log.info(f"loaded {report.heliostats_loaded} heliostats, {report.records_loaded} records from {path}")
    if report.skipped:
        log.warning(
            f"skipped {report.heliostats_skipped} heliostat(s) and {report.records_skipped} record(s) of {path}:"
        )
        whole = [e for e in report.skipped if e.heliostat]
        listed = whole + [e for e in report.skipped if not e.heliostat][: max(MAX_LISTED - len(whole), 0)]
        for entry in listed:
            log.warning(f"  {_relative(entry.file, path)}: {entry.field or '-'}: {entry.reason}")
        if len(report.skipped) > len(listed):
            log.warning(f"  ... and {len(report.skipped) - len(listed)} more: `heliojax inspect {path}` lists them")
    if report.flags:  # kept but suspicious (spots off their target, times of another zone): a warning too
        log.warning(f"{len(report.flags)} suspicious input(s) loaded: `heliojax inspect {path}` lists them")


MAX_LISTED = 5
"""Skipped inputs named one by one before the rest are counted."""


def _relative(file: str, root) -> str:
    try:
        return str(Path(file).relative_to(root))
    except ValueError:
        return str(file)


RECORDS_HEADER = ("heliostat_id", "record_id")
"""Columns of a records file (``heliojax calibrate --records``, ``heliojax plan --records-out``);
an optional third column ``role`` is ``train`` (default) or ``test``."""


def read_record_roles(path: Path) -> dict[str, dict[int, str]]:
    """Heliostat id -> {record id: role} from a records CSV (see :data:`RECORDS_HEADER`).

    Raises:
        DataError: naming the file and row of a missing column, a non-integer record
            id, an unknown role or a record listed twice.
    """
    from .._errors import DataError
    from .._io import is_decimal, read_csv_rows

    header, rows = read_csv_rows(path, "a records CSV")
    if not set(RECORDS_HEADER) <= set(header):
        raise DataError(path, None, f"needs the columns {', '.join(RECORDS_HEADER)} (and optionally role)")
    if not rows:
        raise DataError(path, None, "no records listed")
    roles: dict[str, dict[int, str]] = {}
    for line, row in rows:
        hid = str(row["heliostat_id"] or "").strip()
        try:
            if not is_decimal(str(row["record_id"])):
                raise ValueError
            rid = int(str(row["record_id"]).strip())
        except ValueError:
            raise DataError(path, f"row {line}.record_id", f"not an integer: {row['record_id']!r}") from None
        role = str(row.get("role") or "train").strip()
        if role not in ("train", "test"):
            raise DataError(path, f"row {line}.role", f"{role!r} is neither train nor test")
        if not hid:
            raise DataError(path, f"row {line}.heliostat_id", "empty")
        if rid in roles.setdefault(hid, {}):
            raise DataError(path, f"row {line}", f"record {rid} of {hid} listed twice")
        roles[hid][rid] = role
    return roles


def configure_logging(quiet: bool) -> logging.Logger:
    """Show the library's INFO messages (progress) on stderr as ``[heliojax] ...``;
    only warnings with ``quiet``. Returns the ``heliojax`` logger."""
    logger = logging.getLogger("heliojax")
    for old in [h for h in logger.handlers if getattr(h, "_heliojax_cli", False)]:
        logger.removeHandler(old)  # a handler of an earlier run may hold another stderr
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("[heliojax] %(message)s"))
    handler._heliojax_cli = True  # pyright: ignore[reportAttributeAccessIssue]
    logger.addHandler(handler)
    logger.propagate = False
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    return logger


def enable_compilation_cache(cache_dir: str | os.PathLike | None, command: str | None = None) -> None:
    """Persistent JAX compilation cache so a rerun does not recompile.

    ``cache_dir``: a directory, or None for ``$HELIOJAX_CACHE_DIR`` or
    ``$XDG_CACHE_HOME/heliojax/jax`` (``~/.cache/heliojax/jax`` when that is unset);
    the string ``"none"`` disables it. ``command``: the command starting, whose last
    run's compiled programs are then loaded in the background
    (:func:`heliojax._programs.preload`; :func:`remember_programs` lists them).
    """
    import jax

    from .._errors import ConfigError

    if cache_dir is not None and str(cache_dir).lower() == "none":
        return
    chosen = cache_dir or os.environ.get("HELIOJAX_CACHE_DIR", "").strip() or None  # blank: unset, not a folder "  "
    where = "--cache-dir" if cache_dir else "$HELIOJAX_CACHE_DIR"
    path = None
    try:
        xdg = os.environ.get("XDG_CACHE_HOME", "").strip()  # the XDG rule: an absolute path, else ignored
        cache_home = Path(xdg) if xdg and os.path.isabs(xdg) else Path.home() / ".cache"
        path = Path(chosen or cache_home / "heliojax" / "jax")
        if not _is_utf8(str(path)):  # bytes of another encoding in the name: JAX took it with a TypeError
            raise OSError(0, "the name is not UTF-8 text, which JAX needs")
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK | os.X_OK):
            raise PermissionError(13, "not writable")
    except (OSError, RuntimeError) as e:  # RuntimeError: Path.home() without $HOME or a user entry
        reason = getattr(e, "strerror", None) or str(e)
        if not chosen:  # the default: a convenience, not worth failing a run for
            at = f" in {_shown(path)}" if path is not None else ""  # which folder: $HOME's, $XDG_CACHE_HOME's?
            log.warning(
                f"no compilation cache{at} ({reason}); --cache-dir DIR keeps one, --cache-dir none silences this"
            )
            return
        raise ConfigError(f"{where} {_shown(Path(chosen))}: cannot hold the compilation cache: {reason}") from None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # keep small programs too
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    if command is not None:
        from .._programs import preload

        preload(command)


def remember_programs(command: str) -> None:
    """After a successful run of ``command``: list the compiled programs it ran for its
    next run's :func:`enable_compilation_cache` (nothing when no program was kept)."""
    programs = sys.modules.get("heliojax._programs")  # not imported: no program was compiled
    if programs is not None:
        programs.remember(command)


def _is_utf8(text: str) -> bool:
    """Whether ``text`` (a file name: bytes not UTF-8 are read as lone surrogates) is UTF-8 text."""
    try:
        text.encode()
    except UnicodeEncodeError:
        return False
    return True


def check_output_paths(
    args,
    files: tuple[str, ...] = (),
    directories: tuple[str, ...] = (),
    inside: collections.abc.Iterable[tuple[str, Path]] = (),
) -> None:
    """Before any work: every output file / directory named by ``args`` (attribute
    names; None = not requested) can be written, and so can each file ``inside`` an
    output directory (``(attribute name of the directory, file path)``: a directory or a
    dangling link in its place is refused before the first file is written). Raises
    ConfigError naming the flag."""
    from .._errors import ConfigError

    seen: dict[Path, str] = {}
    files_made: list[tuple[str, Path, Path]] = []  # (flag, path, resolved) of the file outputs
    checks = [(name, getattr(args, name, None), False, True) for name in files]
    checks += [(name, getattr(args, name, None), True, True) for name in directories]
    checks += [(name, path, False, False) for name, path in inside if getattr(args, name, None) is not None]
    for name, value, is_dir, given in checks:
        if value is None or (name == "cache_dir" and str(value).lower() == "none"):
            continue
        flag = "--" + name.replace("_", "-")
        problem = output_path_problem(str(value))
        if problem is not None:
            raise ConfigError(f"{flag}{' ' if str(value).strip() else ''}{_shown(Path(str(value)))}: {problem}")
        path = Path(value)
        # a value as given (not a file inside an output folder, which `OUT/` / name keeps a FolderPath)
        given_as_folder = given and (isinstance(value, FolderPath) or _names_a_folder(str(value)))
        if not is_dir and given_as_folder and not path.is_dir():
            shown = _shown(path) if path.name == ".." else f"{_shown(path)}/"
            raise ConfigError(f"{flag} {shown}: ends with '/', '.' or '..', naming a folder; give a file name")
        try:
            _check_output_path(flag, path, name, is_dir, seen)
            if not is_dir:
                files_made.append((flag, path, path.resolve()))
        except OSError as e:  # a name too long, a loop of links: the flag, not a bare OSError
            raise ConfigError(f"{flag} {_shown(path)}: {e.strerror or e}") from None
    # a file output on the way to another output (`--out out --plot out/fig.png`): the
    # other's folder would be made first and the file could not be written after the work
    for flag, path, resolved in files_made:
        for other, other_flag in seen.items():
            if resolved in other.parents:
                raise ConfigError(
                    f"{flag} {_shown(path)}: {other_flag} writes inside it ({_shown(other)}); "
                    "give the file another name"
                )


_UNSEEN_CATEGORIES = frozenset({"Cc", "Cf", "Zl", "Zp"})
"""Unicode categories of characters a file name must not hold: controls (a line break, a
tab, an escape), format characters (a right-to-left override shows ``gnp.exe`` as
``exe.png``) and line or paragraph separators: a listing shows no such name as it is."""


def output_path_problem(text: str) -> str | None:
    """Why ``text`` is no output path (the command line's and a config's rules: both
    go through here), or None. Refused: an empty name (``Path("")`` is the working
    directory), ``-`` (standard output was meant), ``--`` (the end of the options, which
    argparse drops from ``--out=--``), a name (of the path's folders or file) that
    begins or ends with white space, and a name holding a character of
    :data:`_UNSEEN_CATEGORIES` (``results.h5\\n`` was written as a file whose name ends
    with a line break) or a byte that is not UTF-8."""
    import unicodedata

    if not text.strip():
        return "empty path"
    if text.strip() == "-":
        return "outputs are written to files, not to standard output; give a file name"
    if text.strip() == "--":
        return "'--' is not a value (it ends the options on a command line); give a file name"
    for c in text:
        if not _is_utf8(c):  # a byte that is not UTF-8, read as a lone surrogate: shown as '\ufffd'
            byte = f"0x{ord(c) - 0xDC00:02X}" if 0xDC80 <= ord(c) <= 0xDCFF else f"U+{ord(c):04X}"
            encoding = sys.getfilesystemencoding()
            if encoding.lower().replace("-", "") != "utf8":  # LC_ALL=C with PYTHONUTF8=0: ASCII names only
                return (
                    f"holds a byte beyond ASCII ({byte}), which this process reads as {encoding}, not UTF-8 "
                    "(the locale, e.g. LC_ALL=C); set a UTF-8 locale or PYTHONUTF8=1, or give a plain name"
                )
            return f"is not UTF-8 text (byte {byte}), which no listing shows as it is; give a plain name"
        if unicodedata.category(c) in _UNSEEN_CATEGORIES:
            name = unicodedata.name(c, "")
            code = f"{name}, U+{ord(c):04X}" if name else f"U+{ord(c):04X}"
            return f"holds a control character ({code}), which no listing shows; give a plain name"
    parts = text.replace(os.sep, "/").split("/")
    padded = next((part for part in parts if part != part.strip()), None)
    if padded is not None:  # 'results.h5 ' and 'results.h5' look alike in every listing
        return f"the name '{padded}' begins or ends with white space, which no listing shows; give a plain name"
    return None


INPUT_DIRECTORIES = frozenset({"data_dir", "test_data", "paint_dir", "paint"})
"""Input paths (attribute names of the parsed arguments) that name a directory; every
other input path names a file."""


def check_input_paths(
    options: collections.abc.Mapping[str, argparse.Action],
    args,
    outputs: collections.abc.Collection[str],
    inside: collections.abc.Iterable[tuple[str, Path]] = (),
) -> None:
    """Before any work: every input path option among ``options`` (dest -> action, as
    the CLI's parsers record them; type :func:`path_type`, not one of ``outputs``) that
    ``args`` sets exists and is a directory (:data:`INPUT_DIRECTORIES`) or a regular file, and
    no output of ``outputs`` names that same file (the input
    would be replaced) or lies where a load of an input folder reads
    (:func:`check_not_an_output`), nor does a file the command writes ``inside`` an
    output folder (``(attribute name of the folder, file path)``, as for
    :func:`check_output_paths`: ``accept --results figs/field_map.png --figures figs``
    had replaced its input by a figure). Raises ConfigError naming the flag (the
    metavar of a positional argument)."""
    inside = list(inside)
    from .._errors import ConfigError

    for action in options.values():
        value = getattr(args, action.dest, None)
        if action.type is not path_type or action.dest in outputs or value is None:
            continue
        flag = action.option_strings[-1] if action.option_strings else str(action.metavar or action.dest.upper())
        path = Path(value)
        want_dir = action.dest in INPUT_DIRECTORIES
        try:
            exists, is_dir = path.exists(), path.is_dir()
            if not exists and path.is_symlink():
                target = os.readlink(path)
                raise ConfigError(f"{flag} {_shown(path)}: a symbolic link to {target}, which does not exist")
        except OSError as e:  # a name too long, a loop of links
            raise ConfigError(f"{flag} {_shown(path)}: {e.strerror or e}") from None
        if not exists:
            what = "directory" if want_dir else "file"
            hint = ""
            if action.dest == "results" and path.suffix.lower() in (".h5", ".hdf5"):
                # aim, plan, trace --results: calibrate writes results.h5 only when asked
                hint = f" (heliojax calibrate writes one with --out {_shown(path)})"
            raise ConfigError(f"{flag} {_shown(path)}: no such {what}{hint}")
        if want_dir and not is_dir:
            raise ConfigError(f"{flag} {_shown(path)}: is a file, expected a directory")
        if not want_dir and is_dir:
            raise ConfigError(f"{flag} {_shown(path)}: is a directory, expected a file")
        if not want_dir:
            check_input_file(flag, path)
            _check_not_written_inside(flag, path, args, inside)
        check_not_an_output(flag, path, args, outputs, scanned=want_dir)


def _check_not_written_inside(flag: str, path: Path, args, inside: collections.abc.Iterable[tuple[str, Path]]) -> None:
    """The input file ``path`` is none of the files written ``inside`` an output folder."""
    from .._errors import ConfigError

    for name, output in inside:
        if getattr(args, name, None) is None:
            continue
        try:
            same = output.exists() and os.path.samefile(output, path)
        except (OSError, ValueError):  # not there yet, a name too long: not the input
            same = False
        if same:
            out_flag = "--" + name.replace("_", "-")
            raise ConfigError(
                f"{flag} {_shown(path)}: is {_shown(output)}, a file {out_flag} writes, which would replace "
                f"the input; move the input or give {out_flag} another folder"
            )


def check_input_file(flag: str, path: Path) -> None:
    """An input file ``path`` that exists (flag ``flag``) can be read: a regular file of at
    most :data:`heliojax._io.MAX_INPUT_BYTES` (a FIFO blocks the open, /dev/zero is read
    forever). Raises ConfigError naming the flag."""
    from .._errors import ConfigError
    from .._io import input_file_problem

    try:
        problem = input_file_problem(path)
    except OSError as e:
        raise ConfigError(f"{flag} {_shown(path)}: {e.strerror or e}") from None
    if problem is not None:
        raise ConfigError(f"{flag} {_shown(path)}: {problem}")


def _read_back(output: Path, folder: Path) -> bool:
    """Whether an output at ``output`` lies where a load of the input folder ``folder``
    reads (both resolved through links): in a heliostat's folder at any depth (one
    with ``Properties`` or ``Calibration``; the records CSV's search for
    ``**/Properties`` finds nested ones) or that folder itself (a folder output's
    files go in it), or directly in ``folder`` by a name the scan reads (the tower
    file, the timestamps, the weather CSV). Any other entry is read by nothing:
    ``--out DATA/results.h5``, ``--out DATA/out/results.h5`` (a user working inside
    the download), ``reconstruct``'s default folder run from inside the data."""
    from ..paint._common import TIMESTAMPS_FILE, TOWER_FILE_SUFFIX, WEATHER_CSV_FILE

    try:
        root = folder.resolve()
        inside = output.resolve().relative_to(root).parts
    except (ValueError, OSError, RuntimeError):  # not below it, a loop of links
        return False
    for depth in range(1, len(inside) + 1):
        part = root.joinpath(*inside[:depth])
        if (part / "Properties").is_dir() or (part / "Calibration").is_dir():
            return True  # a heliostat's folder, or inside one
    name = inside[0] if len(inside) == 1 else ""
    return name.endswith(TOWER_FILE_SUFFIX) or name in (TIMESTAMPS_FILE, WEATHER_CSV_FILE)


def check_not_an_output(
    flag: str, path: Path, args, outputs: collections.abc.Iterable[str], *, scanned: bool = False
) -> None:
    """No output (attribute names ``outputs`` of ``args``) is the input file or folder
    ``path`` (also through a link or another name of it): writing it would replace the
    input file, or put the outputs (a compilation cache, figures) among the input's
    files; nor, for a PAINT folder that loads scan (``scanned``), lies inside it where
    its next load reads (:func:`_read_back`: ``calibrate DATA --out DATA/BE36/out``)."""
    from .._errors import ConfigError

    for name in outputs:
        value = getattr(args, name, None)
        if value is None or not str(value).strip() or (name == "cache_dir" and str(value).lower() == "none"):
            continue
        try:
            same = Path(value).exists() and os.path.samefile(value, path)
        except (OSError, ValueError):  # an output not there yet, a name too long: not the input
            same = False
        out_flag = "--" + name.replace("_", "-")
        if not same and scanned and Path(path).is_dir() and _read_back(Path(value), Path(path)):
            raise ConfigError(
                f"{out_flag} {_shown(Path(value))}: inside {flag} {_shown(Path(path))}, an input folder, in a "
                "heliostat's folder or by a name its loads read; write it outside them"
            )
        if not same:
            continue
        if Path(path).is_dir():
            raise ConfigError(
                f"{out_flag} {_shown(Path(value))}: is {flag}, an input folder, among whose files the outputs "
                "would be written; give the output its own folder"
            )
        raise ConfigError(
            f"{out_flag} {_shown(Path(value))}: is {flag}, an input, which writing it would replace; "
            "give the output its own name"
        )


def _shown(path: Path, most: int = 120) -> str:
    """``path`` as shown in a message: at most ``most`` characters."""
    text = str(path)
    return text if len(text) <= most else f"{text[: most // 2]}...{text[-most // 2 :]}"


def _check_output_path(flag: str, path: Path, name: str, is_dir: bool, seen: dict[Path, str]) -> None:
    """One output of :func:`check_output_paths`; ``seen``: resolved file -> its flag."""
    from .._errors import ConfigError
    from .._io import remove_stale_temporaries

    _check_no_dangling_link(flag, path)
    _check_not_in_embedded_data(flag, path)
    same = seen.setdefault(path.resolve(), flag)  # a folder of figures named like a file output too
    if same != flag:
        raise ConfigError(f"{flag} {path}: {same} names the same path; give each output its own")
    if is_dir and path.exists() and not path.is_dir():
        raise ConfigError(f"{flag} {path}: exists and is not a directory")
    if not is_dir and path.is_dir():
        raise ConfigError(f"{flag} {path}: is a directory, expected a file name")
    if not is_dir and path.exists() and not path.is_file():  # /dev/null, /dev/stdout, a FIFO
        raise ConfigError(
            f"{flag} {path}: exists and is not a regular file (a device, a pipe or a socket, which "
            "writing the output beside it and renaming it onto its name would replace); give a file name"
        )
    if not is_dir and path.is_file() and (not os.access(path, os.W_OK) or not path.stat().st_mode & 0o222):
        raise ConfigError(f"{flag} {path}: exists and is read-only")
    if not is_dir and name == "plot":
        _check_figure_format(flag, path)
    ancestor = path if is_dir else path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        _check_no_dangling_link(flag, path, ancestor)
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ConfigError(f"{flag} {path}: {ancestor} is not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag} {path}: {ancestor} is not writable")
    _check_a_file_can_be_made(flag, path, ancestor)
    folder = path if is_dir else path.parent
    if folder.is_dir() and name != "cache_dir":
        for stale in remove_stale_temporaries(folder):
            log.info(f"removed {stale}, left by an interrupted run")


def _check_not_in_embedded_data(flag: str, path: Path) -> None:
    """An output is not written inside heliojax's embedded data
    (:func:`heliojax.paint.default_data_dir`), the input of every command given no data
    folder: ``calibrate --report <its tower file>`` had replaced that file by a summary
    (every later run then failed), unchecked because no input path was given."""
    from .._errors import ConfigError
    from ..paint import default_data_dir

    data = default_data_dir()
    try:
        inside = path.resolve().is_relative_to(data.resolve())
    except (OSError, RuntimeError):  # a loop of links: named by the checks that follow
        return
    if inside:
        raise ConfigError(
            f"{flag} {_shown(path)}: inside heliojax's embedded data ({_shown(data)}), the input of every "
            "command run without a data folder; write it elsewhere"
        )


def _check_a_file_can_be_made(flag: str, path: Path, folder: Path) -> None:
    """A file can be made in ``folder`` (tried: an empty temporary file, removed at once).
    ``os.access`` says yes to root everywhere, also in /proc or /sys, where no file can be
    made: the command ran for minutes and then failed on writing its output. The probe
    carries this process in its name (:func:`heliojax._io.new_temporary`), so that one
    left by a ``kill -9`` is removed by the next run at once, not after an hour."""
    from .._errors import ConfigError
    from .._io import make_temporary, new_temporary

    probe = new_temporary(folder, "probe")
    try:
        make_temporary(probe)
    except OSError as e:
        raise ConfigError(
            f"{flag} {_shown(path)}: no file can be made in {_shown(folder)}: {e.strerror or e}"
        ) from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(probe)


def _check_no_dangling_link(flag: str, path: Path, link: Path | None = None) -> None:
    """An output ``path`` (or its folder ``link``) that is a symbolic link must point at
    something that exists: a live link is written through (the file it points at is
    replaced, see :func:`heliojax._io.atomic_write`); a dangling one, often a stale link
    to a disk not mounted, is refused rather than replaced by a file of its own or
    followed into folders made up on the way."""
    from .._errors import ConfigError

    link = path if link is None else link
    if link.is_symlink() and not link.exists():
        where = "" if link == path else f"{link} is "
        raise ConfigError(
            f"{flag} {path}: {where}a symbolic link to {os.readlink(link)}, which does not exist; "
            "remove the link or create what it points at"
        )


def heliostat_id(value: str) -> str:
    """An argparse ``type``: a heliostat id as the loader reads it, a heliostat folder's
    name (the one rule: :func:`heliojax._io.heliostat_id_problem`)."""
    from .._io import heliostat_id_problem

    problem = heliostat_id_problem(value)
    if problem:
        raise argparse.ArgumentTypeError(f"{shown_value(value)} is not a heliostat id ({problem})")
    return value


def _check_figure_format(flag: str, path: Path) -> None:
    """A figure's format (its suffix; none is PNG) must be one matplotlib writes."""
    from matplotlib.backend_bases import FigureCanvasBase

    from .._errors import ConfigError

    suffix = path.suffix.lstrip(".").lower()
    formats = FigureCanvasBase.get_supported_filetypes()
    if suffix and suffix not in formats:
        raise ConfigError(f"{flag} {path}: unknown figure format {suffix!r}; use one of {', '.join(sorted(formats))}")


def path_type(value: str) -> Path:
    """An argparse ``type``: a file or directory name; an empty one (``Path("")`` is the
    working directory, never what was meant) or one with a NUL byte is refused."""
    if not str(value).strip():
        raise argparse.ArgumentTypeError("empty path")
    if "\0" in str(value):
        raise argparse.ArgumentTypeError(f"{value!r}: a path cannot hold a NUL byte")
    return FolderPath(value) if _names_a_folder(str(value)) else Path(value)


def _names_a_folder(text: str) -> bool:
    """Whether a path as given names a folder by its form: a final ``/``, ``.`` or ``..``
    (``Path`` drops a final ``/`` and ``/.``: ``x.h5/.`` was written as a file ``x.h5``)."""
    last = text.rstrip("/" + os.sep).replace(os.sep, "/").rsplit("/", 1)[-1]
    return text.endswith(("/", os.sep)) or last in (".", "..")


class FolderPath(type(Path())):
    """A path given with a final ``/`` (or ``/.``, ``/..``), which ``Path`` drops or keeps as
    a name: it names a folder (an output file ``x.h5/`` is refused, not written as ``x.h5``)."""


_ISO_DATE_TIME = re.compile(
    r"\d{4}-\d{2}-\d{2}(?:[T ]\d{2}(?::\d{2}(?::\d{2}(?:[.,]\d{1,6})?)?)?(?:Z|[+-]\d{2}(?::?\d{2})?)?)?", re.ASCII
)


def is_iso_date_time(text: str) -> bool:
    """Whether ``text`` is written ``YYYY-MM-DD[THH[:MM[:SS[.ffffff]]]][Z|+hh:mm]``, the form
    the date options name (at most 6 fractional digits: Python dropped the 7th on, a
    nanosecond time silently read as another). Python's ``fromisoformat`` also reads ``20230331`` (at midnight:
    an inclusive ``--end 20230331`` left out its own day), week dates (``2023-W13``, a
    Monday) and any run of digits (100 ones are 1111-11-11T11:11:11.111111)."""
    return _ISO_DATE_TIME.fullmatch(text) is not None


def _is_ascii_number(text: str, special: bool = False) -> bool:
    """Whether ``text`` is a number written as a command line writes one: ASCII digits,
    a sign, a point, an exponent (:func:`heliojax._io.is_decimal`; with ``special`` also
    nan and inf, which the range check names). Python's int() and float() also take
    ``1_000``, digits of other scripts (``١٢``, full-width ``１２``): read silently as
    another number than the one meant, or as one where none was meant."""
    from .._io import is_decimal

    return is_decimal(text) or (special and text.strip().lower().lstrip("+-") in ("nan", "inf", "infinity"))


LARGEST_INTEGER = 2**31 - 1
"""Largest value of an integer option without its own maximum (counts, ids, steps)."""


def target_name(value: object) -> str:
    """An argparse ``type``: a target of the tower file by name (``receiver``), by the
    rule the tower file's loader applies (:func:`heliojax._limits.target_name_problem`:
    ``--targets =HYPERLINK(...)`` went into plan.csv's ``target`` column, a formula to a
    spreadsheet)."""
    from .._limits import target_name_problem

    if not isinstance(value, str):
        raise argparse.ArgumentTypeError(f"expected a target name, got {shown_value(value)}")
    problem = target_name_problem(value)
    if problem:
        raise argparse.ArgumentTypeError(f"{shown_value(value)} is not a target name ({problem})")
    return value


def integer(minimum: int | None = None, maximum: int | None = None) -> _Integer:
    """An argparse ``type``: an integer in ``[minimum, maximum]`` (from a command
    line string or a config number), else a message naming the range; no ``maximum``
    is :data:`LARGEST_INTEGER` (a config's 1e308 is an integer, one no program takes)."""
    return _Integer(minimum, LARGEST_INTEGER if maximum is None else maximum)


@dataclasses.dataclass(frozen=True)
class _Integer:
    """:func:`integer`'s parser (a class, not a closure: the parsers are made anew for
    every command line, and a closure would be a new function each time)."""

    minimum: int | None
    top: int
    __name__ = "integer"  # argparse and the config loader name the kind by it

    def __call__(self, value: str | int | float) -> int:
        if isinstance(value, bool) or (isinstance(value, str) and not _is_ascii_number(value)):
            raise argparse.ArgumentTypeError(f"expected an integer, got {shown_value(value)}")
        try:
            number = int(value)
        except (TypeError, ValueError, OverflowError):  # OverflowError: a config's inf
            raise argparse.ArgumentTypeError(f"expected an integer, got {shown_value(value)}") from None
        if isinstance(value, float) and number != value:
            raise argparse.ArgumentTypeError(f"expected an integer, got {value!r}")
        if (self.minimum is not None and number < self.minimum) or number > self.top:
            shown = str(value if isinstance(value, float) else number)  # not 1e308's 309 digits
            shown = shown if len(shown) <= 40 else f"{shown[:20]}...({len(shown)} digits)"  # nor 4000 typed ones
            raise argparse.ArgumentTypeError(f"{shown} is outside [{self.minimum}, {self.top}]".replace("None", "..."))
        return number


def number(
    minimum: float | None = None, maximum: float | None = None, *, above: bool = False, below: bool = False
) -> _Number:
    """An argparse ``type``: a finite number in ``[minimum, maximum]`` (open at the
    bottom with ``above``, at the top with ``below``), else a message naming the range."""
    return _Number(minimum, maximum, above, below)


@dataclasses.dataclass(frozen=True)
class _Number:
    """:func:`number`'s parser (a class, as :class:`_Integer`)."""

    minimum: float | None
    maximum: float | None
    above: bool
    below: bool
    __name__ = "number"  # argparse and the config loader name the kind by it

    def __call__(self, value: str | float) -> float:
        if isinstance(value, bool) or (isinstance(value, str) and not _is_ascii_number(value, special=True)):
            raise argparse.ArgumentTypeError(f"expected a number, got {shown_value(value)}")
        try:
            x = float(value)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected a number, got {shown_value(value)}") from None
        low_ok = self.minimum is None or (x > self.minimum if self.above else x >= self.minimum)
        high_ok = self.maximum is None or (x < self.maximum if self.below else x <= self.maximum)
        if not math.isfinite(x) or not low_ok or not high_ok:
            brackets = ("(" if self.above else "[", ")" if self.below else "]")
            raise argparse.ArgumentTypeError(
                f"{x} is outside {brackets[0]}{self.minimum}, {self.maximum}{brackets[1]}".replace("None", "...")
            )
        return x


MAX_DECLINATION_DEG = 23.45
"""The sun's declination stays within +-23.45 degrees."""


def check_sun_possible(azimuth_deg: float | None, elevation_deg: float | None, latitude_deg: float) -> None:
    """ConfigError unless the sun can stand at ``azimuth_deg`` (0 = south, positive east) and
    ``elevation_deg`` at ``latitude_deg``: its declination must lie within the tropics."""
    from .._errors import ConfigError

    if azimuth_deg is None or elevation_deg is None:
        return
    az, el, lat = (math.radians(x) for x in (azimuth_deg, elevation_deg, latitude_deg))
    north = -math.cos(el) * math.cos(az)
    declination = math.degrees(math.asin(max(-1.0, min(1.0, math.sin(lat) * math.sin(el) + math.cos(lat) * north))))
    if abs(declination) > MAX_DECLINATION_DEG:
        raise ConfigError(
            f"--sun-azimuth {azimuth_deg:g} --sun-elevation {elevation_deg:g}: the sun never stands there at "
            f"latitude {latitude_deg:.2f} (declination {declination:.1f}, beyond +-{MAX_DECLINATION_DEG})"
        )


_PENDING_INTERRUPT: list[KeyboardInterrupt] = []
"""A Ctrl-C, SIGTERM or SIGHUP the command has received (:func:`note_interrupt`): its
KeyboardInterrupt may have been raised where Python swallows exceptions (a garbage
collector callback, JAX's among them, prints "Exception ignored" and carries on)."""


def note_interrupt(interrupt: KeyboardInterrupt | None) -> None:
    """Remember ``interrupt`` (None: forget any) for :func:`raise_if_interrupted`."""
    _PENDING_INTERRUPT[:] = [] if interrupt is None else [interrupt]


def raise_if_interrupted() -> None:
    """Raise the interrupt the command received, if any: called before outputs are
    written and when the command returns, so that an interrupt swallowed where it was
    raised still stops the command (exit 130, 143 or 129, outputs not written)."""
    if _PENDING_INTERRUPT:
        raise _PENDING_INTERRUPT[0]


@contextlib.contextmanager
def staged_outputs(args: argparse.Namespace, names: tuple[str, ...]) -> collections.abc.Iterator[None]:
    """Within the block, the output paths ``args.<name>`` are temporaries (see
    :func:`heliojax._io.staged_paths`); when it completes, they are renamed onto the
    outputs together and each written output is logged. A command stopped while
    writing leaves the previous set of outputs as it was, never half a new set."""
    from .._io import staged_paths

    finals = [getattr(args, n) for n in names]
    raise_if_interrupted()
    with staged_paths(finals) as temps:
        for n, t in zip(names, temps, strict=True):
            setattr(args, n, t)
        try:
            yield
            raise_if_interrupted()  # before the temporaries are renamed onto the outputs
        finally:
            for n, f in zip(names, finals, strict=True):
                setattr(args, n, f)
    for f in finals:
        if f is not None:
            log.info(f"wrote {f}")


MAX_PLANT_OFFSET_M = 1_000.0
"""Largest distance (m) between the plant reference point of the tower file that ``aim`` or
``plan`` uses and the ENU origin of the fit they aim (``results.h5``'s ``origin_lla``, the
reference point of the tower file of the calibration): one plant's files place it within
metres of itself, two plants are kilometres apart."""


def read_plant_tower(path, origin_lla) -> typing.Any:
    """The tower file ``path`` (default: the embedded Jülich tower file) of the plant
    whose fit has the ENU origin ``origin_lla`` (WGS84 deg, deg, m). Raises ConfigError
    naming ``--tower`` when its plant reference point is more than
    :data:`MAX_PLANT_OFFSET_M` from that origin: aim points of another plant (the
    embedded tower for a fit of another plant put every aim point kilometres away)."""
    from .._errors import ConfigError
    from ..paint import default_data_dir, read_tower
    from ..paint._common import _distance_m

    tower = read_tower(path or default_data_dir() / "WRI1030197-tower-measurements.json")
    origin = tuple(float(x) for x in origin_lla)
    gap = _distance_m(tuple(float(x) for x in tower.origin_lla), origin)  # pyright: ignore[reportArgumentType]
    if not gap <= MAX_PLANT_OFFSET_M:
        which = f"--tower {path}" if path else "the embedded Jülich tower file (no --tower)"
        raise ConfigError(
            f"{which}: its plant reference point is {gap / 1000:.3g} km from the fit's origin "
            f"{[round(x, 6) for x in origin]} (results.h5 origin_lla): the tower file of another plant; "
            "give the plant's with --tower"
        )
    return tower


MOVED_POSITION_M = 0.1
"""A heliostat of a PAINT folder farther than this (m) from the position its fit used is
named: a survey is good to centimetres, so the folder comes from another survey, or
another plant, than the fit (hostile-input trials 4 and 5: 22 m and 55 m went
unnoticed)."""


def warn_moved(source: str, ids, positions, results, what_is_used: str) -> None:
    """Warn of the heliostats ``ids`` whose ``positions`` ``(N, 3)`` (ENU m, read from
    ``source``) lie more than :data:`MOVED_POSITION_M` from the ones the fit in
    ``results`` (a :class:`heliojax.CalibrationResults`) used; ``what_is_used`` ends
    the message (which of the two the command goes on with)."""
    import numpy as np

    from .._errors import few_names

    row = {h: i for i, h in enumerate(ids)}
    shared = [(k, row[h]) for k, h in enumerate(results.ids) if h in row]
    if not shared:
        return
    fit_rows, own_rows = (np.array(x) for x in zip(*shared, strict=True))
    gap = np.linalg.norm(
        np.asarray(positions, float).reshape(-1, 3)[own_rows] - np.asarray(results.geometry.position)[fit_rows],
        axis=-1,
    )
    moved = [f"{results.ids[k]} ({d:.3g} m)" for k, d in zip(fit_rows, gap, strict=True) if not d <= MOVED_POSITION_M]
    if moved:
        log.warning(
            f"{source}: {few_names(moved)} {'lies' if len(moved) == 1 else 'lie'} farther than "
            f"{MOVED_POSITION_M:g} m from the position the fit used (another survey or plant than the fit's?); "
            f"{what_is_used}"
        )
