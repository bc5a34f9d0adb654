"""``heliojax aim``: motor counts for a calibrated fleet (thin over
:func:`heliojax.aim_results`)."""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import logging
import re
from pathlib import Path

import numpy as np

from ._common import (
    add_cache_argument,
    check_sun_possible,
    enable_compilation_cache,
    integer,
    is_iso_date_time,
    number,
    path_type,
    read_plant_tower,
    shown_value,
    staged_outputs,
    target_name,
)

log = logging.getLogger(__name__)

OUTPUT_FILES = ("out", "h5", "plot")
OUTPUT_DIRS = ("cache_dir",)
PARTNERS = {"start": ("end",), "sun_azimuth": ("sun_elevation",)}
"""Options that go with another (a config's ``end`` is dropped with its ``start``, its
``sun_elevation`` with its ``sun_azimuth``: ``--date`` on the command line had dropped
only the azimuth, and the error then named flags the user had not typed)."""


def default_outputs(args) -> None:
    """The schedule goes beside the fit it was computed from unless ``--out`` names a file."""
    if args.out is None:
        args.out = Path(args.results).parent / "aim.csv"


"""Output paths checked before any work (attribute names of the parsed arguments)."""

EXAMPLES = """examples:
  heliojax calibrate --out out/results.h5 && heliojax aim out/results.h5 --date 2023-06-21 --out out/aim.csv
  heliojax aim out/results.h5 --start 2023-06-21T06:00 --end 2023-06-21T18:00 --step-minutes 15 --plot out/aim.png
  heliojax aim out/results.h5 --sun-azimuth -20 --sun-elevation 40 --target solar_tower_juelich_lower"""


def _utc(value: str) -> dt.datetime:
    """``YYYY-MM-DD[THH:MM[:SS]][Z|+hh:mm]``; naive means UTC; an instant the library
    takes (:func:`heliojax._limits.instant_problem`: 1970 to 2200-01-01, UTC; an instant
    of 1900 passed here and ended in a traceback of :func:`heliojax.aim_results`)."""
    from .._limits import instant_problem

    try:
        if not is_iso_date_time(value):
            raise ValueError
        t = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"not an ISO date-time: {shown_value(value)}") from e
    t = t if t.tzinfo is not None else t.replace(tzinfo=dt.UTC)
    problem = instant_problem(t)  # in UTC: 2199-12-31T23:00-05:00 is in 2200
    if problem is not None:
        raise argparse.ArgumentTypeError(f"{value!r}: {problem}")
    return t.astimezone(dt.UTC)  # written and computed in UTC from here on


def _utc_instant(value: str) -> dt.datetime:
    """:func:`_utc` of a date-time with its time of day: ``--time 2023-06-21`` named midnight
    UTC, a sun below the horizon, and aimed every heliostat at night."""
    if re.fullmatch(r"\s*\d{4}-\d{2}-\d{2}\s*", value):
        raise argparse.ArgumentTypeError(
            f"{value.strip()}: a date without a time of day; give one (e.g. {value.strip()}T12:00Z), "
            f"or --date {value.strip()} for the whole day"
        )
    return _utc(value)


def utc_day(value: str) -> dt.datetime:
    """``YYYY-MM-DD``: a whole UTC day (midnight UTC); a time or an offset is refused
    (the day it names would not be the UTC day)."""
    text = value.strip()
    if len(text) != 10 or not is_iso_date_time(text):
        raise argparse.ArgumentTypeError(
            f"not a day: {shown_value(value)} (YYYY-MM-DD, a UTC day; give instants with --start/--end or --time)"
        )
    return _utc(text)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "aim",
        help="motor counts that put each calibrated heliostat's beam on an aim point, with error bars",
        description=(
            "Read a fitted fleet (results.h5 of `heliojax calibrate`), compute for every heliostat and "
            "instant the motor counts that put its beam on the aim point (the receiver by default) with "
            "the calibrated inverse kinematics, the predicted pointing uncertainty (mrad: radial scale and 95 % "
            "radius, from the fit's parameter covariance, the drift since the fit, the sky gap to the fitted "
            "records' suns where the fit asked for it, and the fitted tails) and "
            "flags (counts outside the actuator range, sun low, no usable fit, "
            "aim point not reached, a sun or an instant outside what the fit's records cover). Writes a CSV "
            "(one row per heliostat and instant), optionally HDF5 and a plot."
        ),
    )
    p.add_argument("results", type=path_type, metavar="RESULTS_H5", help="results.h5 of `heliojax calibrate`")
    when = p.add_mutually_exclusive_group()
    when.add_argument(
        "--date", type=utc_day, help="a whole day (UTC, YYYY-MM-DD), with --step-minutes (default: today)"
    )
    when.add_argument("--start", type=_utc, help="first instant, ISO date-time (UTC), with --end")
    when.add_argument("--time", type=_utc_instant, help="one instant, ISO date-time (UTC)")
    when.add_argument("--sun-azimuth", type=number(-360.0, 360.0), help="sun azimuth in degrees (0 = south, east +)")
    p.add_argument("--end", type=_utc, help="last instant with --start")
    p.add_argument("--sun-elevation", type=number(0.0, 90.0, above=True), help="sun elevation in degrees")
    p.add_argument(
        "--step-minutes",
        type=number(0.0, 1440.0, above=True),
        default=None,
        help=f"instant spacing of --date or --start/--end (default {DEFAULT_STEP_MINUTES:g})",
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--target",
        type=target_name,
        default=None,
        help="aim point: this target's centre in the tower file (default: receiver)",
    )
    where.add_argument(
        "--aim-csv",
        type=path_type,
        metavar="FILE",
        help="per-heliostat aim points instead of --target: CSV heliostat_id,east_m,north_m,up_m (ENU of the "
        "fit's origin) or heliostat_id,lat_deg,lon_deg,alt_m (WGS84)",
    )
    p.add_argument("--tower", type=path_type, help="tower file (default: the embedded Jülich tower file)")
    p.add_argument(
        "--min-sun-elevation", type=number(-90.0, 90.0), default=5.0, help="flag instants with a lower sun (degrees)"
    )
    p.add_argument(
        "--max-sky-gap",
        type=number(0.0, 180.0),
        default=20.0,  # heliojax.MAX_SKY_GAP_DEG (this module imports no JAX); tests/test_aim.py checks
        help="flag commands whose sun is farther than this from the sun of every record the heliostat was "
        "fitted to (degrees): the model is extrapolated there",
    )
    p.add_argument("--max-instants", type=integer(1, 100_000), default=10_000, help="refuse longer schedules")
    p.add_argument(
        "--out",
        type=path_type,
        default=None,
        metavar="FILE",
        help="CSV of the commands (default: aim.csv beside RESULTS_H5)",
    )
    p.add_argument("--h5", type=path_type, default=None, metavar="FILE", help="HDF5 with the full arrays")
    p.add_argument("--plot", type=path_type, default=None, metavar="FILE", help="figure of the error bars (PNG)")
    add_cache_argument(p)
    p.add_argument("--quiet", action="store_true", help="no messages on stderr")


DEFAULT_STEP_MINUTES = 30.0
"""``--step-minutes`` when not given (instants of ``--date`` or ``--start``/``--end``)."""


def _utc_text(t: dt.datetime) -> str:
    """ISO 8601 UTC with a ``Z``, to the microsecond where the instant has a fraction of
    a second (written as whole seconds, the CSV named another instant than the one aimed
    for)."""
    return t.strftime("%Y-%m-%dT%H:%M:%S" + (".%f" if t.microsecond else "") + "Z")


def time_window(args) -> list[dt.datetime]:
    """The instants of ``--start``/``--end`` or of the whole day ``--date`` (default:
    today, UTC), ``--step-minutes`` apart, at most ``--max-instants``."""
    from .._errors import ConfigError

    minutes = DEFAULT_STEP_MINUTES if args.step_minutes is None else args.step_minutes
    step = dt.timedelta(minutes=minutes)
    if step < dt.timedelta(seconds=1):
        raise ConfigError(f"--step-minutes {minutes:g}: instants must be at least a second apart")
    if args.start is not None:
        if args.end is None or args.end < args.start:
            raise ConfigError("--start needs an --end at or after it")
        start, end = args.start, args.end
    else:
        day = args.date or dt.datetime.now(dt.UTC)
        start = day.replace(hour=0, minute=0, second=0, microsecond=0)
        if start.date() == dt.date.max:
            raise ConfigError(f"--date {start.date()}: the day after it is out of range")
        end = start + dt.timedelta(days=1) - dt.timedelta(seconds=1)
    n = int((end - start) / step) + 1
    if n > args.max_instants:
        raise ConfigError(f"{n} instants exceed --max-instants {args.max_instants}; use a larger --step-minutes")
    return [start + k * step for k in range(n)]


def _instants(args, origin_lla):
    """``(times or None, sun (N, 3))`` for the requested instants."""
    import jax.numpy as jnp
    import numpy as np

    from .._errors import ConfigError
    from .._geometry import sun_direction
    from .._sun import solar_position

    one = "--time" if args.time is not None else "--sun-azimuth/--sun-elevation"
    if args.step_minutes is not None and (args.time is not None or args.sun_azimuth is not None):
        raise ConfigError(f"--step-minutes spaces the instants of --date or --start/--end; {one} gives one instant")
    if args.sun_azimuth is not None or args.sun_elevation is not None:
        if args.sun_azimuth is None or args.sun_elevation is None:
            raise ConfigError("--sun-azimuth and --sun-elevation go together")
        check_sun_possible(args.sun_azimuth, args.sun_elevation, float(origin_lla[0]))
        sun = sun_direction(jnp.deg2rad(jnp.array([args.sun_azimuth])), jnp.deg2rad(jnp.array([args.sun_elevation])))
        return None, sun
    times = [args.time] if args.time is not None else time_window(args)
    unix = np.array([t.timestamp() for t in times])
    lat, lon, alt = (float(x) for x in origin_lla)
    return times, solar_position(jnp.asarray(unix), lat, lon, alt).direction_enu()


MAX_AIM_DEPTH_M = 10.0
"""Deepest an aim point may lie below the lowest heliostat's position (m): deeper, the
beam would go into the ground (a sign or datum mistake in the CSV)."""

MIN_AIM_DISTANCE_M = 10.0
"""Nearest an aim point may lie to its heliostat's position (m): a few mirror sizes (a
Juelich mirror is 3.2 m x 2.6 m). Nearer, the "aim point" is on or beside the mirror
itself, a coordinate mistake in the CSV (every receiver or target is tens of metres
away or more)."""


def _aim_points_csv(path: Path, ids: tuple[str, ...], origin_lla, heliostat_position: np.ndarray) -> np.ndarray:
    """``(H, 3)`` ENU aim points (m) of the heliostats ``ids`` from a CSV (see ``--aim-csv``)."""
    from .._errors import DataError
    from .._geometry import MAX_FIELD_EXTENT_M, wgs84_to_enu
    from .._io import heliostat_id_problem, is_decimal, read_csv_rows

    enu_cols, lla_cols = ("east_m", "north_m", "up_m"), ("lat_deg", "lon_deg", "alt_m")
    header, rows = read_csv_rows(path, "an aim-point CSV")
    has_enu, has_lla = set(enu_cols) <= set(header), set(lla_cols) <= set(header)
    if "heliostat_id" not in header or not (has_enu or has_lla):
        raise DataError(path, None, f"needs heliostat_id and {', '.join(enu_cols)} or {', '.join(lla_cols)}")
    if has_enu and has_lla:
        raise DataError(path, None, "has both ENU and WGS84 columns: give the aim points in one of them")
    # a column of the other frame beside a full set (lat_deg beside east_m,north_m,up_m): which
    # frame was meant is unknown; any other column would be dropped without a word
    other = lla_cols if has_enu else enu_cols
    for c in header:
        if c in other:
            raise DataError(
                path,
                c,
                f"{'a WGS84' if has_enu else 'an ENU'} column beside the {'ENU' if has_enu else 'WGS84'} columns "
                f"{', '.join(enu_cols if has_enu else lla_cols)}: give the aim points in one frame",
            )
        if c not in ("heliostat_id", *enu_cols, *lla_cols):
            raise DataError(
                path, str(c), f"unknown column; known: heliostat_id and {', '.join(enu_cols)} or {', '.join(lla_cols)}"
            )
    if not rows:
        raise DataError(path, None, "no aim points (a header only)")
    cols = enu_cols if has_enu else lla_cols
    points: dict[str, np.ndarray] = {}
    lines: dict[str, int] = {}
    for line, row in rows:
        hid = str(row["heliostat_id"] or "").strip()
        if problem := heliostat_id_problem(hid):
            raise DataError(path, f"row {line}.heliostat_id", f"{hid!r} is no heliostat id ({problem})")
        for c in cols:
            if not is_decimal(str(row[c] or "")):
                raise DataError(path, f"row {line}.{c}", f"not a decimal number: {row[c]!r}")
        xyz = np.array([float(str(row[c])) for c in cols])
        if not np.all(np.isfinite(xyz)):
            raise DataError(path, f"row {line}", "non-finite coordinate")
        if cols == lla_cols and not (abs(xyz[0]) <= 90.0 and abs(xyz[1]) <= 180.0):
            raise DataError(path, f"row {line}", f"latitude {xyz[0]:g} / longitude {xyz[1]:g} out of range")
        if hid in points:
            raise DataError(path, f"row {line}", f"a second aim point for {hid} (the first in row {lines[hid]})")
        points[hid], lines[hid] = xyz, line
    unknown = [h for h in points if h not in ids]
    if unknown:
        raise DataError(
            path, f"row {lines[unknown[0]]}.heliostat_id", f"not in the results: {', '.join(map(repr, unknown[:5]))}"
        )
    missing = [h for h in ids if h not in points]
    if missing:
        raise DataError(path, "heliostat_id", f"no aim point for {', '.join(missing)}")
    out = np.stack([points[h] for h in ids])
    enu = out if cols == enu_cols else np.asarray(wgs84_to_enu(out, np.asarray(origin_lla)))
    # hypot, not a sum of squares: a coordinate of 1e308 overflows that (a RuntimeWarning to the user)
    far = ~(np.hypot(np.hypot(enu[:, 0], enu[:, 1]), enu[:, 2]) <= MAX_FIELD_EXTENT_M)  # NaN too
    if far.any():
        h = ids[int(np.argmax(far))]
        raise DataError(path, f"row {lines[h]}", f"the aim point of {h} is over {MAX_FIELD_EXTENT_M / 1e3:g} km away")
    near = np.linalg.norm(enu - heliostat_position, axis=-1) < MIN_AIM_DISTANCE_M
    if near.any():
        i = int(np.argmax(near))
        raise DataError(
            path,
            f"row {lines[ids[i]]}",
            f"the aim point of {ids[i]} is {np.linalg.norm(enu[i] - heliostat_position[i]):.1f} m from the "
            f"heliostat, nearer than {MIN_AIM_DISTANCE_M:g} m: on or beside its mirror (a coordinate mistake?)",
        )
    lowest = float(np.min(heliostat_position[:, 2]))
    deep = enu[:, 2] < lowest - MAX_AIM_DEPTH_M
    if deep.any():
        h = ids[int(np.argmax(deep))]
        raise DataError(
            path,
            f"row {lines[h]}",
            f"the aim point of {h} is {lowest - enu[int(np.argmax(deep)), 2]:.1f} m below the lowest heliostat: "
            "underground (a sign or height datum mistake?)",
        )
    return enu


def summary_line(ok, std, radius95, flags: dict, ids, status) -> str:
    """The printed summary: the median uncertainty of the commands without a flag, or,
    when there is none, why (no usable fit, and the flags the rows carry): never a NaN."""
    good = ok & np.isfinite(std) & np.isfinite(radius95)
    head = f"{int(ok.sum())} of {ok.size} commands without a flag"
    if good.any():
        return (
            f"{head}; median predicted pointing uncertainty {np.median(std[good]):.3f} mrad (radial scale), "
            f"95 % radius {np.median(radius95[good]):.3f} mrad"
        )
    carried = ", ".join(f"{k} {int(v.sum())}" for k, v in flags.items() if v.any()) or "none"
    if flags["unreliable"].all():
        counts: dict[str, int] = {}
        for s in status:
            counts[str(s)] = counts.get(str(s), 0) + 1
        why = (
            f"no heliostat has a usable fit (status {', '.join(f'{k}: {n} of {len(ids)}' for k, n in counts.items())}; "
            "a converged fit is unusable when the file flags it, no fitted record has a time for the drift, or, "
            "with a sky-gap term, none has a sun)"
        )
    else:
        why = "every command carries a flag"
    return f"{head}: no pointing uncertainty to report, {why}; flags of the rows: {carried}"


def run(args) -> int:
    import jax.numpy as jnp
    import numpy as np

    from .._aim import aim_results
    from .._errors import ConfigError
    from .._geometry import direction_to_azimuth_elevation, enu_to_wgs84, wgs84_to_enu
    from .._io import atomic_h5, atomic_write
    from .._progress import activity
    from .._results import load_results
    from ..optics import target_from_tower

    enable_compilation_cache(args.cache_dir, args.command)
    results = load_results(args.results)
    origin = np.asarray(results.attrs["origin_lla"], float)
    tower = read_plant_tower(args.tower, origin)
    args.target = args.target or "receiver"
    target = target_from_tower(tower, args.target)
    if args.aim_csv is not None:
        position = np.asarray(results.geometry.position, float)
        centre = jnp.asarray(_aim_points_csv(args.aim_csv, results.ids, origin, position))
        args.target = f"points of {args.aim_csv.name}"
    else:
        centre = wgs84_to_enu(enu_to_wgs84(target.centre, jnp.asarray(tower.origin_lla)), jnp.asarray(origin))
    if args.end is not None and args.start is None:
        raise ConfigError("--end needs --start")
    times, sun = _instants(args, origin)
    log.info(f"aiming {len(results.ids)} heliostats at {args.target} for {sun.shape[0]} instant(s)")
    unix = None if times is None else np.array([t.timestamp() for t in times])
    if times is None and (results.drift_mrad2_per_day > 0.0 or results.creep_mrad2_per_day2 > 0.0):
        log.warning(
            "a sun position without a time: the predicted uncertainty leaves out the fleet's drift since the fit "
            f"({results.drift_mrad2_per_day:.2g} mrad^2 per day, creep {results.creep_mrad2_per_day2:.2g} mrad^2 "
            "per day^2), which --time, --date or --start include"
        )
    with activity("aiming", logger=log):
        r = aim_results(
            results,
            sun,
            centre,
            unix_time=unix,
            min_sun_elevation_deg=args.min_sun_elevation,
            max_sky_gap_deg=args.max_sky_gap,
        )
    counts = np.asarray(r.counts)
    std = np.asarray(r.pointing_std_mrad)
    radius95 = np.asarray(r.pointing_radius_mrad(0.95))
    az, el = (np.degrees(np.asarray(x)) for x in direction_to_azimuth_elevation(sun))
    flags = {
        "counts_out_of_range": np.asarray(r.counts_out_of_range),
        "sun_low": np.broadcast_to(np.asarray(r.sun_low)[None, :], counts.shape[:2]),
        "unreliable": np.broadcast_to(np.asarray(r.unreliable)[:, None], counts.shape[:2]),
        "unreachable": np.asarray(r.unreachable),
        "beyond_calibrated_sky": np.asarray(r.beyond_calibrated_sky),
        "uncertainty_above_nominal": np.asarray(r.uncertainty_above_nominal),
        "before_fit": np.asarray(r.before_fit),
        "long_after_fit": np.asarray(r.long_after_fit),
    }
    ok = np.asarray(r.ok)
    others = np.any([v for k, v in flags.items() if k != "beyond_calibrated_sky"], axis=0)
    beyond_only = flags["beyond_calibrated_sky"] & ~others
    if beyond_only.any():
        log.warning(
            f"{int(beyond_only.sum())} command(s) of {int(beyond_only.any(axis=1).sum())} heliostat(s) flagged only "
            f"beyond_calibrated_sky: the sun is over {args.max_sky_gap:g} deg from every record they were fitted to "
            "(measure there, see heliojax plan, or allow it with --max-sky-gap)"
        )
    with staged_outputs(args, ("out", "h5", "plot")):  # a set: an interrupt leaves the previous one
        with atomic_write(args.out, newline="") as f:
            w = csv.writer(f)
            w.writerow(
                [
                    "heliostat_id",
                    "time_utc",
                    "sun_azimuth_deg",
                    "sun_elevation_deg",
                    "axis_1_counts",
                    "axis_2_counts",
                    "pointing_std_mrad",
                    "pointing_r95_mrad",
                    "ok",
                    "flags",
                ]
            )
            for i, hid in enumerate(results.ids):
                for j in range(counts.shape[1]):
                    c = counts[i, j]
                    w.writerow(
                        [
                            hid,
                            "" if times is None else _utc_text(times[j]),
                            f"{az[j]:.4f}",
                            f"{el[j]:.4f}",
                            int(round(c[0])) if np.isfinite(c[0]) else "",
                            int(round(c[1])) if np.isfinite(c[1]) else "",
                            f"{std[i, j]:.4f}" if np.isfinite(std[i, j]) else "",
                            f"{radius95[i, j]:.4f}" if np.isfinite(radius95[i, j]) else "",
                            int(ok[i, j]),
                            ";".join(k for k, v in flags.items() if v[i, j]),
                        ]
                    )
        log.info(f"{int(ok.sum())} of {ok.size} commands without a flag")
        if args.h5 is not None:
            import h5py

            with atomic_h5(args.h5) as f:
                f.attrs["target"] = args.target
                f.attrs["origin_lla"] = origin
                f.attrs["tail_dof"] = r.error_law.tail_dof
                f.attrs["outlier_fraction"] = r.error_law.outlier_fraction
                f.attrs["outlier_scale"] = r.error_law.outlier_scale
                f.create_dataset("heliostat_id", data=np.array(results.ids, dtype=object), dtype=h5py.string_dtype())
                if times is not None:
                    f.create_dataset("unix_time", data=np.array([t.timestamp() for t in times])).attrs["units"] = "s"
                f.create_dataset("sun_enu", data=np.asarray(sun))
                f.create_dataset("aim_point_enu", data=np.asarray(centre)).attrs["units"] = "m"
                f.create_dataset("counts", data=counts)
                f.create_dataset("pointing_cov_mrad2", data=np.asarray(r.pointing_cov_mrad2)).attrs["units"] = "mrad^2"
                f.create_dataset("ok", data=ok)
                f.create_dataset("sky_gap_deg", data=np.asarray(r.sky_gap_deg)).attrs["units"] = "deg"
                for k, v in flags.items():
                    f.create_dataset(f"flags/{k}", data=v)
        if args.plot is not None:
            from .._plotting import plot_aim, save_figure

            distance = np.linalg.norm(np.asarray(centre)[None, :] - np.asarray(results.geometry.position), axis=-1)
            hours = None if times is None else np.array([(t - times[0]).total_seconds() / 3600.0 for t in times])
            fig = plot_aim(
                list(results.ids),
                np.asarray(r.pointing_cov_mrad2),
                ok,
                distance,
                hours,
                times[0] if times else None,
                error_law=r.error_law,
            )
            save_figure(fig, args.plot)
    print(summary_line(ok, std, radius95, flags, results.ids, results.status))
    return 0
