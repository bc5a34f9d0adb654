"""``heliojax inspect``: load PAINT data, tabulate it, report uncalibrated errors."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np

from ._common import add_cache_argument, add_data_argument, enable_compilation_cache, load_fleet, path_type

EXAMPLES = """examples:
  heliojax inspect
  heliojax inspect ../shared/data/paint --centroid helios --plot out/uncalibrated.png"""

OUTPUT_FILES = ("plot",)
OUTPUT_DIRS = ("cache_dir",)
"""Output paths checked before any work (attribute names of the parsed arguments)."""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "inspect",
        help="load PAINT data and print records, dates and uncalibrated beam errors per heliostat",
        description=(
            "Load a PAINT-layout directory (the embedded real subset by default), print a table per "
            "heliostat (records, date range, uncalibrated beam pointing error of the nominal "
            "linear-actuator and Stone models, median and max) and the load report."
        ),
    )
    add_data_argument(p)
    add_cache_argument(p)
    p.add_argument(
        "--plot",
        type=path_type,
        metavar="FILE",
        help="write a box plot of the uncalibrated errors, PNG (default: none)",
    )


def _date(t: float) -> str:
    if not np.isfinite(t):
        return "?"
    return dt.datetime.fromtimestamp(float(t), dt.UTC).strftime("%Y-%m-%d")


def _stat(reduce, x: np.ndarray) -> float:
    """``reduce(x)``, NaN for a heliostat without usable records."""
    return float(reduce(x)) if x.size else float("nan")


def run(args) -> int:
    from .._kinematics import nominal_model
    from ..fitting import fleet_beam_errors_mrad

    enable_compilation_cache(args.cache_dir, args.command)
    fleet = load_fleet(args)
    n = len(fleet.ids)
    err = {}
    for kind in ("actuator", "stone8"):
        err[kind] = np.asarray(fleet_beam_errors_mrad(nominal_model(kind, fleet.counts.dtype), fleet))
    t = np.asarray(fleet.context.unix_time)
    mask = np.asarray(fleet.mask)
    flagged = {
        Path(f.file).parts[-3]
        for f in fleet.report.flags
        if len(Path(f.file).parts) >= 3 and Path(f.file).parts[-2] == "Properties"
    }
    print(
        f"{'heliostat':<10} {'records':>7}  {'first':<10}  {'last':<10}  "
        f"{'actuator med':>12} {'max':>8}  {'stone med':>9} {'max':>8}  [mrad, uncalibrated]"
    )
    for i in range(n):
        m = mask[i]
        ti = t[i][m]
        ea = err["actuator"][i][m]
        es = err["stone8"][i][m]
        note = "  (flagged, see load report)" if fleet.ids[i] in flagged else ""
        note += "  (no usable records)" if not m.any() else ""
        print(
            f"{fleet.ids[i]:<10} {int(m.sum()):>7}  {_date(np.nanmin(ti) if np.isfinite(ti).any() else np.nan):<10}  "
            f"{_date(np.nanmax(ti) if np.isfinite(ti).any() else np.nan):<10}  "
            f"{_stat(np.median, ea):>12.1f} {_stat(np.max, ea):>8.1f}  "
            f"{_stat(np.median, es):>9.1f} {_stat(np.max, es):>8.1f}{note}"
        )
    all_a = err["actuator"][mask]
    print(
        f"{'fleet':<10} {int(mask.sum()):>7}  {'':<10}  {'':<10}  {_stat(np.median, all_a):>12.1f} "
        f"{_stat(np.max, all_a):>8.1f}  {_stat(np.median, err['stone8'][mask]):>9.1f} "
        f"{_stat(np.max, err['stone8'][mask]):>8.1f}"
    )
    print()
    print(fleet.report.format())
    if args.plot is not None:
        from .._plotting import plot_error_per_heliostat, save_figure

        fig = plot_error_per_heliostat(
            list(fleet.ids[:n]),
            err["actuator"][:n],
            title="uncalibrated beam pointing error, nominal linear-actuator model",
        )
        save_figure(fig, args.plot)
        print(f"wrote {args.plot}")
    return 0
