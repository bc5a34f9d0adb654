"""``heliojax fetch``: download PAINT data from a STAC catalogue (thin over :mod:`heliojax.paint`)."""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import sys

from .._errors import HeliojaxError
from ._common import check_not_an_output, integer, is_iso_date_time, number, path_type, shown_value

COLLECTIONS = ("properties", "calibration", "deflectometry")
"""``heliojax.paint.COLLECTIONS`` (kept here so that ``--help`` needs no JAX; a test
checks they agree)."""
CALIBRATION_ASSETS = (
    "calibration_properties",
    "flux_image",
    "flux_centered_image",
    "cropped_image",
    "raw_image",
)
"""``heliojax.paint.CALIBRATION_ASSETS`` (a test checks they agree)."""
EXAMPLES = """examples:
  heliojax fetch --out paint --heliostats AA39,BE36 --start 2023-01-01 --end 2023-03-31
  heliojax fetch catalog.json --out paint --collections properties,calibration --assets all --max-items 20"""
PAINT_CATALOGUE = "https://paint-database.org/WRI1030197/WRI1030197-catalog-stac.json"


def _csv(value: str) -> list[str]:
    """An argparse ``type``: comma-separated names, at least one (``,,,`` fetched nothing and said so nowhere)."""
    names = [v.strip() for v in value.split(",") if v.strip()]
    if not names:
        raise argparse.ArgumentTypeError(f"{value[:40]!r} names nothing: give comma-separated names")
    return names


@dataclasses.dataclass(frozen=True)
class _CsvOf:
    """An argparse ``type``: comma-separated names, each one of ``choices`` (or ``extra``).
    (A class, not a closure: parsers are made anew for every command line.)"""

    choices: tuple[str, ...]
    what: str
    extra: tuple[str, ...] = ()

    def __call__(self, value: str) -> list[str]:
        names = _csv(value)
        unknown = [n for n in names if n not in self.choices and n not in self.extra]
        if unknown:
            shown = ", ".join(repr(n[:60]) for n in unknown[:5])
            raise argparse.ArgumentTypeError(
                f"unknown {self.what} {shown}; choose from {','.join(self.choices + self.extra)}"
            )
        return names


def _source(value: str) -> str:
    """An argparse ``type``: a non-empty catalogue URL or path (an empty one would be the
    working directory, never what was meant)."""
    if not value.strip():
        raise argparse.ArgumentTypeError("empty: give a catalogue URL or path")
    return value


def _when(value: str) -> dt.datetime | dt.date:
    """``YYYY-MM-DD`` (a whole day) or an ISO 8601 date-time (naive means UTC)."""
    try:
        if not is_iso_date_time(value):
            raise ValueError
        if len(value) == 10:
            return dt.date.fromisoformat(value)
        t = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"not a date or ISO date-time: {shown_value(value)}") from e
    if t.tzinfo is not None:  # compared in UTC: an offset may carry year 1 or 9999 out of range
        try:
            t.astimezone(dt.UTC)
        except OverflowError:
            raise argparse.ArgumentTypeError(f"{value!r} in UTC falls outside the years 1-9999") from None
    return t


MAX_TIMEOUT_S = 86400.0
"""Longest ``--timeout``: a day per request (the socket takes no more than about 68 years,
and 1e10 s failed inside it, with a traceback)."""

OUTPUT_FILES = ()
OUTPUT_DIRS = ("out",)
"""Output paths checked before any work (attribute names of the parsed arguments)."""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "fetch",
        help="download PAINT data from a STAC catalogue into PAINT's folder layout",
        description=(
            "Walk a PAINT-style STAC catalogue (root -> heliostat catalogues -> properties, "
            "calibration, deflectometry collections -> items -> assets) and download the chosen "
            "assets into OUT as <H>/Properties, <H>/Calibration, <H>/Deflectometry plus the tower "
            "file. Interrupted runs resume; every file is verified (size/checksum when the "
            "catalogue gives them, JSON parses) and written atomically. Unsafe hrefs are refused. "
            "Exit 2 when a file fails or a heliostat asked for is not in the catalogue (the files "
            "that did come are kept: the same command again retries the rest)."
        ),
    )
    p.add_argument(
        "source",
        metavar="SOURCE",
        nargs="?",
        type=_source,
        default=PAINT_CATALOGUE,
        help=f"root catalogue: URL or path to its JSON file or folder (default: {PAINT_CATALOGUE})",
    )
    p.add_argument("--out", metavar="DIR", type=path_type, required=True, help="output folder")
    p.add_argument("--heliostats", metavar="IDS", type=_csv, help="comma-separated heliostat ids (default: all)")
    p.add_argument(
        "--collections",
        metavar="NAMES",
        type=_CsvOf(tuple(COLLECTIONS), "collection"),
        default=["properties", "calibration"],
        help=f"comma-separated, from {','.join(COLLECTIONS)} (default: properties,calibration)",
    )
    p.add_argument(
        "--assets",
        metavar="KEYS",
        type=_CsvOf(tuple(CALIBRATION_ASSETS), "calibration asset", ("all",)),
        default=["calibration_properties"],
        help=f"calibration asset keys, from {','.join(CALIBRATION_ASSETS)} or 'all' (default: calibration_properties)",
    )
    p.add_argument("--start", type=_when, help="earliest item datetime, YYYY-MM-DD or ISO (UTC)")
    p.add_argument("--end", type=_when, help="latest item datetime, YYYY-MM-DD (inclusive) or ISO (UTC)")
    p.add_argument(
        "--max-items", type=integer(1), metavar="N", help="at most N calibration items per heliostat (earliest)"
    )
    p.add_argument("--no-resume", dest="resume", action="store_false", help="download everything again")
    p.add_argument("--no-tower", dest="tower", action="store_false", help="skip the tower-measurements file")
    p.add_argument("--workers", type=integer(1, 64), default=8, help="parallel downloads")
    p.add_argument(
        "--timeout",
        type=number(0.0, MAX_TIMEOUT_S, above=True),
        default=60.0,
        help=f"seconds per request, in (0, {MAX_TIMEOUT_S:g}]",
    )
    p.add_argument(
        "--same-host-only",
        action="store_true",
        help="refuse an HTTP redirect to another host (default: followed; https -> http never is)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")


def run(args) -> int:
    from pathlib import Path

    from ..paint import fetch_catalog

    if "://" not in args.source and Path(args.source).exists():  # a local catalogue: its folder is an input
        folder = Path(args.source) if Path(args.source).is_dir() else Path(args.source).parent
        check_not_an_output("SOURCE", folder, args, OUTPUT_DIRS)
    assets = list(CALIBRATION_ASSETS) if "all" in args.assets else args.assets

    def progress(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    try:
        report = fetch_catalog(
            args.source,
            args.out,
            heliostats=args.heliostats,
            collections=args.collections,
            calibration_assets=assets,
            start=args.start,
            end=args.end,
            max_items=args.max_items,
            resume=args.resume,
            include_tower=args.tower,
            workers=args.workers,
            timeout_s=args.timeout,
            progress=None if args.quiet else progress,
            same_host_only=args.same_host_only,
        )
    except (HeliojaxError, ValueError) as e:
        print(f"heliojax fetch: error: {e}", file=sys.stderr)
        return 2
    for w in report.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if report.missing:
        print(f"heliojax fetch: --heliostats: not in the catalogue: {', '.join(report.missing)}", file=sys.stderr)
    for href, reason in report.failed:
        print(f"heliojax fetch: failed {href}: {reason}", file=sys.stderr)
    if report.failed:
        print(
            "heliojax fetch: run the same command again to retry the failed downloads "
            "(a file whose catalogue entry is broken fails again until the catalogue is mended)",
            file=sys.stderr,
        )
    return 0 if report.ok else 2  # a data error, as every command's (the files that did come are kept)


def main(argv=None) -> int:  # pragma: no cover - convenience for `python -m heliojax.cli._fetch`
    parser = argparse.ArgumentParser(prog="heliojax")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return run(args)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
