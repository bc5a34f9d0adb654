"""``heliojax plan``: which calibration measurements to take next (thin over
:func:`heliojax.plan_calibration`)."""

from __future__ import annotations

import csv
import datetime as dt
import logging
from pathlib import Path

from .._limits import EARLIEST_YEAR, LATEST_YEAR
from ._aim import _utc, time_window, utc_day
from ._common import (
    RECORDS_HEADER,
    add_cache_argument,
    enable_compilation_cache,
    integer,
    number,
    option_label,
    path_type,
    read_plant_tower,
    report_load,
    staged_outputs,
    target_name,
    warn_moved,
)

log = logging.getLogger(__name__)

OUTPUT_FILES = ("out", "ranking", "records_out", "plot")
OUTPUT_DIRS = ("cache_dir",)
PARTNERS = {"start": ("end",)}
"""Options that go with another (a config's ``end`` is dropped with its ``start``)."""
DEFAULT_STEP_MINUTES = 30.0
DEFAULT_MAX_INSTANTS = 2_000
"""Defaults of ``--step-minutes`` and ``--max-instants``, applied after the check that
``--paint-dir`` was not given them (their argparse default is None: "not given")."""


def default_outputs(args) -> None:
    """The schedule goes beside the fit it was computed from unless ``--out`` names a file."""
    if args.out is None:
        args.out = Path(args.results).parent / "plan.csv"


"""Output paths checked before any work (attribute names of the parsed arguments)."""

EXAMPLES = """examples:
  heliojax calibrate --out out/results.h5
  heliojax plan out/results.h5 --date 2024-06-21 --budget 4 --plot out/plan.png --ranking out/ranking.csv
  heliojax plan out/results.h5 --start 2024-06-21T05:00 --end 2024-06-23T19:00 --targets multi_focus_tower
  heliojax calibrate ../shared/data/paint --records pool.csv --out pool.h5
  heliojax plan pool.h5 --paint-dir ../shared/data/paint --before 2023-09-01 --start-from prior --budget 8 \\
      --records-out chosen.csv && heliojax calibrate ../shared/data/paint --records chosen.csv"""


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "plan",
        help="plan the next calibration measurements: which instants and targets, which heliostats first",
        description=(
            "For every heliostat of a fitted fleet (results.h5 of `heliojax calibrate`), choose --budget "
            "camera-target measurements among candidates that most reduce the predicted pointing uncertainty "
            "over the operating envelope (a year of sun positions weighted by clear-sky DNI, aiming at the "
            "receiver): greedy I-optimal design with the model's Jacobian, the fit's covariance (or the fleet "
            "prior), the fit's noise and a model discrepancy learnt from the fit's residuals. Candidates "
            "are future instants x calibration targets, or, with --paint-dir and --before, the heliostat's "
            "existing records before a date (a retrospective plan, "
            "to be judged on the later records with `heliojax calibrate --records`). Writes the schedule "
            "(CSV), the fleet ranking (which heliostats most need measuring) and optionally a plot."
        ),
    )
    p.add_argument("results", type=path_type, metavar="RESULTS_H5", help="results.h5 of `heliojax calibrate`")
    p.add_argument("--budget", type=integer(1, 1000), default=4, help="measurements per heliostat")
    when = p.add_mutually_exclusive_group()
    when.add_argument(
        "--date",
        type=utc_day,
        help="candidate instants: a whole day (UTC, YYYY-MM-DD), with --step-minutes (default: today)",
    )
    when.add_argument("--start", type=_utc, help="candidate instants: first one, ISO date-time (UTC), with --end")
    p.add_argument("--end", type=_utc, help="last candidate instant with --start")
    p.add_argument(
        "--step-minutes",
        type=number(0.0, 1440.0, above=True),
        default=None,
        help=f"instant spacing, minutes (default: {DEFAULT_STEP_MINUTES:g})",
    )
    p.add_argument(
        "--targets",
        nargs="+",
        type=target_name,
        default=None,
        metavar="NAME",
        help="calibration targets to plan on (default: every planar target of the tower file)",
    )
    p.add_argument(
        "--paint-dir",
        type=path_type,
        default=None,
        metavar="DIR",
        help="candidates are this PAINT directory's existing records (those before --before) instead of instants",
    )
    p.add_argument("--before", type=_utc, default=None, help="with --paint-dir: only records before this instant")
    p.add_argument(
        "--start-from",
        choices=("posterior", "prior"),
        default="posterior",
        help="posterior: add to what each fit knows; prior: plan every heliostat from scratch from the fleet prior",
    )
    p.add_argument(
        "--model-discrepancy",
        choices=("estimate", "none"),
        default="estimate",
        help="estimate: plan for a model that is not exact, with a discrepancy process over the mirror normal "
        "learnt from the fit's residuals (heliojax.discrepancy_from_results); none: trust the model exactly",
    )
    p.add_argument(
        "--age-by-drift",
        action="store_true",
        help="grow each candidate's noise with its age at the use time (--before, or the last candidate "
        "instant) under the fit's pointing drift (results.h5's drift_mrad2_per_day and creep_mrad2_per_day2), "
        "so that recent records count more (heliojax.aged_noise_mrad); default: every candidate at the fit's noise",
    )
    p.add_argument(
        "--target",
        type=target_name,
        default="receiver",
        help="operating aim point: this target's centre in the tower file",
    )
    p.add_argument("--tower", type=path_type, help="tower file (default: the embedded Jülich tower file)")
    p.add_argument(
        "--envelope-year",
        type=integer(EARLIEST_YEAR, LATEST_YEAR),  # the library's span of instants (1900 and 2200 were taken)
        default=2023,
        help=f"year of the operating envelope ({EARLIEST_YEAR} to {LATEST_YEAR}, UTC)",
    )
    p.add_argument("--envelope-day-step", type=integer(1, 365), default=5, help="every N-th day of the envelope year")
    p.add_argument(
        "--min-sun-elevation",
        type=number(0.0, 90.0),
        default=10.0,
        help="lowest sun (degrees, 0-90: a measurement needs the sun up) of the envelope and of candidate instants "
        "or records",
    )
    p.add_argument(
        "--max-instants",
        type=integer(1, 20_000),
        default=None,
        help=f"refuse longer candidate windows (default: {DEFAULT_MAX_INSTANTS})",
    )
    p.add_argument(
        "--out", type=path_type, default=None, metavar="FILE", help="schedule CSV (default: plan.csv beside RESULTS_H5)"
    )
    p.add_argument(
        "--ranking", type=path_type, default=None, metavar="FILE", help="CSV of the heliostats, most in need first"
    )
    p.add_argument(
        "--records-out",
        type=path_type,
        default=None,
        metavar="FILE",
        help="with --paint-dir: records CSV for `heliojax calibrate --records` "
        "(chosen, and from the posterior the fit's own training records: train; at/after --before: test)",
    )
    p.add_argument(
        "--plot", type=path_type, default=None, metavar="FILE", help="figure of the predicted uncertainty (PNG)"
    )
    add_cache_argument(p)
    p.add_argument("--quiet", action="store_true", help="no messages on stderr")


def _nothing_to_plan(sun_elevation_deg, unix, min_elevation_deg: float, label: str, targets: tuple[str, ...]) -> str:
    """The warning for a window in which no candidate is usable: why nothing can be
    planned (the schedule is its header alone, exit 0; the summary line on standard
    output alone said so before).

    Args:
        sun_elevation_deg: ``(N,)`` the sun's elevation (deg) at the window's instants.
        unix: ``(N,)`` the instants (Unix s, UTC).
        min_elevation_deg: the lowest sun allowed (deg); ``label`` names its option.
        targets: the targets the candidates aim at.
    """
    import numpy as np

    elevation = np.asarray(sun_elevation_deg, float)
    window = f"the window {_iso(float(unix[0]))} .. {_iso(float(unix[-1]))} ({len(unix)} instant(s))"
    if not (elevation >= min_elevation_deg).any():
        return (
            f"no instant of {window} has the sun above {label} {min_elevation_deg:g} deg (highest "
            f"{float(np.max(elevation)):.1f} deg): nothing planned; choose a window in daylight"
        )
    return (
        f"no heliostat can aim at {', '.join(targets)} at any instant of {window} with the sun above {label} "
        f"{min_elevation_deg:g} deg (the commands fall outside the actuators' range): nothing planned"
    )


def _warn_fitted_after_the_cut(args, results, fleet, times) -> None:
    """Warn where a retrospective plan (``--before``) starts from a fit that trained on
    records at or after the cut: from its posterior (the default) the plan then knows
    what a plant at the cut could not have, and the study is not retrospective. The
    plan is still made; ``--records-out`` holds those records out (role ``test``)."""
    import numpy as np

    from .._errors import few_names
    from .._fleet import records_among
    from .._results import SPLIT_CODES

    if args.before is None or args.start_from != "posterior" or "split" not in results.records:
        return
    trained = np.asarray(results.records["split"]) == SPLIT_CODES["train"]
    trained &= np.asarray(results.fitted, bool)[:, None]
    known = records_among(fleet.ids, fleet.record_id, results.ids, results.records["record_id"], trained)
    late = known & np.isfinite(times) & (times >= args.before.timestamp())
    if not late.any():
        return
    rows = np.flatnonzero(late.any(axis=1))
    named = few_names([f"{fleet.ids[r]} ({int(late[r].sum())})" for r in rows])
    log.warning(
        f"--before {args.before.isoformat()}: the fit in {Path(args.results).name} trained on records at or after "
        f"it for {len(rows)} heliostat(s): {named}; the plan starts from that posterior, so it is not "
        "retrospective (--records-out holds those records out as test). Fit the records before the cut first "
        "(heliojax calibrate --records FILE), or plan from the fleet prior (--start-from prior)"
    )


def _warn_before_fit(args, results, unix) -> None:
    """Warn (a plan is still made) where candidate instants ``unix`` (s) lie before a
    heliostat's first fitted record, as :func:`heliojax.aim_results` flags ``before_fit``
    (:func:`heliojax._aim.outside_fit_time`): a measurement in the past cannot be taken
    (``--date 1990-06-21`` was planned without a word); a retrospective plan is what
    ``--paint-dir`` with ``--before`` is for."""
    import numpy as np

    from .._aim import fitted_time_span, outside_fit_time
    from .._errors import few_names

    before, after = outside_fit_time(results, unix)
    times = fitted_time_span(results)
    if before is None or after is None or times is None:
        return
    dest, flag = ("date", "--date") if args.date is not None else ("start", "--start")
    window = f"{_iso(float(unix[0]))} .. {_iso(float(unix[-1]))}"
    label = option_label(args, dest, flag) if getattr(args, dest) is not None else "the window (today, UTC)"
    late = np.flatnonzero(after.all(axis=1))
    if late.size:  # as aim flags long_after_fit, which a plan had not said
        log.warning(
            f"{label}: candidate instants {window} lie further after the last fitted record of {late.size} "
            f"heliostat(s) ({few_names([f'{results.ids[i]} {_iso(float(times[1][i]))[:10]}' for i in late])}) "
            "than the fit's records span: the heliostats may have drifted since, which the predicted "
            "uncertainties (from the fit's covariance) leave out"
        )
    if not before.any():
        return
    early = np.flatnonzero(before.any(axis=1))
    first = times[0]
    log.warning(
        f"{label}: candidate instants {window} lie before the first fitted record of {len(early)} heliostat(s) "
        f"({few_names([f'{results.ids[i]} {_iso(float(first[i]))[:10]}' for i in early])}): "
        "measurements planned in the past cannot be taken; for a retrospective plan use --paint-dir with --before"
    )


def _iso(unix: float) -> str:
    if unix != unix:  # NaN
        return ""
    return dt.datetime.fromtimestamp(unix, dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def run(args) -> int:
    import jax.numpy as jnp
    import numpy as np

    from .._errors import ConfigError, DataError
    from .._fleet import records_among
    from .._geometry import direction_to_azimuth_elevation, enu_to_wgs84, wgs84_to_enu
    from .._io import atomic_write
    from .._plan import (
        candidates_at_targets,
        candidates_from_records,
        discrepancy_from_results,
        operating_envelope,
        plan_calibration,
    )
    from .._progress import activity
    from .._results import SPLIT_CODES, load_results
    from .._sun import solar_position
    from ..optics import target_from_tower
    from ..paint import load_paint_directory

    if args.paint_dir is None and (args.before is not None or args.records_out is not None):
        raise ConfigError("--before and --records-out need --paint-dir")
    if args.paint_dir is not None:
        given = [
            flag
            for flag, value in (
                ("--date", args.date),
                ("--start", args.start),
                ("--targets", args.targets),
                ("--step-minutes", args.step_minutes),
                ("--max-instants", args.max_instants),
            )
            if value is not None
        ]
        if given:
            raise ConfigError(f"--paint-dir plans among existing records: no {', '.join(given)}")
    args.step_minutes = DEFAULT_STEP_MINUTES if args.step_minutes is None else args.step_minutes
    args.max_instants = DEFAULT_MAX_INSTANTS if args.max_instants is None else args.max_instants
    if args.end is not None and args.start is None:
        raise ConfigError("--end needs --start")
    enable_compilation_cache(args.cache_dir, args.command)
    results = load_results(args.results)
    if not np.asarray(results.fitted, bool).any():
        statuses = ", ".join(sorted(set(results.status)))
        raise ConfigError(
            f"{args.results}: no heliostat has a usable fit ({statuses}): neither a posterior nor a fleet prior "
            "to plan from (a plan from it predicted 500 mrad from a 'learnt' discrepancy of 0)"
        )
    origin = np.asarray(results.attrs["origin_lla"], float)
    tower = read_plant_tower(args.tower, origin)
    # before any candidate is chosen or announced (round 7: "planning 2 measurement(s)"
    # stood before this error)
    sun_e, w_e = operating_envelope(
        origin, year=args.envelope_year, day_step=args.envelope_day_step, min_elevation_deg=args.min_sun_elevation
    )
    if sun_e.shape[0] == 0:
        raise ConfigError(
            f"--min-sun-elevation {args.min_sun_elevation:g}: the sun never rises that high in "
            f"{args.envelope_year} at latitude {float(origin[0]):.2f} (the operating envelope is empty)"
        )

    def centre(name: str) -> np.ndarray:
        plane = target_from_tower(tower, name)
        lla = enu_to_wgs84(plane.centre, jnp.asarray(tower.origin_lla))
        return np.asarray(wgs84_to_enu(lla, jnp.asarray(origin)))

    discrepancy = None
    if args.model_discrepancy == "estimate":
        known = set(tower.targets)
        missing = [t for t in results.target_names if t not in known]
        if missing:  # their records' mirror normals are unknown: left out of what is learnt
            which = f"--tower {args.tower}" if args.tower else "the embedded Jülich tower file"
            log.warning(
                f"{which} has no target {', '.join(missing)} of the fit (results.h5 target_names): the fit's "
                f"records on {'it' if len(missing) == 1 else 'them'} do not inform the model discrepancy"
            )
        centres_r = np.stack(
            [centre(t) if t in known else np.full(3, np.nan) for t in results.target_names] or [np.full(3, np.nan)]
        )
        try:
            with activity("learning the model discrepancy", logger=log):
                discrepancy = discrepancy_from_results(results, centres_r)
        except DataError as e:
            raise ConfigError(f"{e}; plan with --model-discrepancy none") from e
        log.info(
            f"model discrepancy learnt from the fit's residuals: {float(discrepancy.amplitude_mrad):.3f} mrad, "
            f"correlation length {float(discrepancy.length):.3f} (chord of mirror normals), "
            f"beside {float(discrepancy.nugget_mrad):.3f} mrad noise"
        )

    aim_point = centre(args.target)
    h = len(results.ids)
    record_ids = target_of = None
    fleet = None
    if args.paint_dir is not None:
        with activity(f"loading {args.paint_dir}", logger=log):
            fleet = load_paint_directory(args.paint_dir, heliostats=results.ids, origin=origin)
        report_load(fleet.report, args.paint_dir)
        warn_moved(
            f"--paint-dir {args.paint_dir}",
            fleet.ids,
            fleet.geometry.position,
            results,
            "the plan uses the fit's positions",
        )
        times = np.asarray(fleet.context.unix_time)
        usable = np.asarray(fleet.mask) & np.isfinite(times)
        if args.before is not None:
            usable &= times < args.before.timestamp()
            if not usable.any():
                raise ConfigError(f"--before {args.before.isoformat()}: no record of {args.paint_dir} is before it")
        # Not candidates: records the fit put before a change point (a past state) and,
        # where the plan starts from the fit's posterior, records it was fitted to
        # (measured already: planning them again counted their information twice, and
        # the plan's predicted gain with it). From the fleet prior (--start-from prior, a
        # retrospective study of which records to have taken) they are candidates.
        if "record_id" in results.records:
            _warn_fitted_after_the_cut(args, results, fleet, times)
            fitted = np.zeros(np.shape(results.records["record_id"]), bool)
            if "split" in results.records and args.start_from == "posterior":
                fitted |= np.asarray(results.records["split"]) == SPLIT_CODES["train"]
            if "superseded" in results.records:
                fitted |= np.asarray(results.records["superseded"], bool)
            known = records_among(fleet.ids, fleet.record_id, results.ids, results.records["record_id"], fitted)
            if (usable & known).any():
                log.info(
                    f"{int((usable & known).sum())} record(s) of {args.paint_dir} lie before the fit's change "
                    f"points{' or are its own training records' if args.start_from == 'posterior' else ''}: "
                    "not candidates"
                )
            usable &= ~known
            if not usable.any():
                raise ConfigError(
                    f"--paint-dir {args.paint_dir}: every record is one the fit used or superseded; nothing new to plan"
                )
        _, sun_el = direction_to_azimuth_elevation(fleet.context.sun)
        low = usable & (np.degrees(np.asarray(sun_el)) < args.min_sun_elevation)
        if low.any():
            log.info(
                f"{int(low.sum())} record(s) of {args.paint_dir} with the sun below --min-sun-elevation "
                f"{args.min_sun_elevation:g} deg: not candidates"
            )
            usable &= ~low
            if not usable.any():
                raise ConfigError(
                    f"--min-sun-elevation {args.min_sun_elevation:g}: no record of {args.paint_dir} left as a candidate"
                )
        candidates, record_ids = candidates_from_records(fleet, results.ids, usable)
        rows = [list(fleet.ids).index(i) if i in fleet.ids else -1 for i in results.ids]
        names = np.asarray(fleet.target_names + ("",))
        target_of = np.stack(
            [names[np.asarray(fleet.target_index)[r]] if r >= 0 else np.full(record_ids.shape[1], "") for r in rows]
        )
        source = f"{int(np.asarray(candidates.valid).sum())} existing records of {args.paint_dir}"
    else:
        instants = time_window(args)
        targets = tuple(args.targets or tower.planar_target_names)
        not_planar = [t for t in targets if t not in tower.planar_target_names]
        if not_planar:
            raise ConfigError(
                f"--targets {', '.join(not_planar)}: not a planar calibration target of {Path(tower.source).name} "
                f"(a measurement needs one: {', '.join(tower.planar_target_names)})"
            )
        unix = np.array([t.timestamp() for t in instants])
        _warn_before_fit(args, results, unix)
        lat, lon, alt = (float(x) for x in origin)
        position = solar_position(jnp.asarray(unix), lat, lon, alt)
        sun = position.direction_enu()
        centres = np.stack([centre(t) for t in targets])
        known = tuple(results.target_names)
        candidates = candidates_at_targets(
            results.model,
            results.geometry,
            sun,
            jnp.asarray(centres),
            unix_time=unix,
            target_index=np.array([known.index(t) if t in known else -1 for t in targets]),
            min_elevation_deg=args.min_sun_elevation,
        )
        if not np.asarray(candidates.valid).any():
            elevation = np.degrees(np.asarray(position.elevation))
            label = option_label(args, "min_sun_elevation", "--min-sun-elevation")
            log.warning(_nothing_to_plan(elevation, unix, args.min_sun_elevation, label, targets))
        target_of = np.broadcast_to(np.tile(np.asarray(targets), len(instants)), (h, len(instants) * len(targets)))
        source = f"{len(instants)} instants x {len(targets)} targets"
    log.info(f"planning {args.budget} measurement(s) for {h} heliostats among {source} ({args.start_from})")
    with activity("planning", logger=log):
        plan, _ = plan_calibration(
            results,
            candidates,
            envelope_sun=sun_e,
            envelope_weight=w_e,
            aim_point=jnp.asarray(aim_point),
            budget=args.budget,
            start=args.start_from,
            discrepancy=discrepancy,
            drift=args.age_by_drift,
            use_unix_time=None if args.before is None else args.before.timestamp(),
        )
    chosen = np.asarray(plan.chosen)
    before = np.asarray(plan.uncertainty_before_mrad)
    after = np.asarray(plan.uncertainty_after_mrad)
    unix_c = np.asarray(candidates.context.unix_time)
    az, el = (np.degrees(np.asarray(x)) for x in direction_to_azimuth_elevation(candidates.context.sun))
    with staged_outputs(args, ("out", "ranking", "records_out", "plot")):  # a set, as calibrate
        with atomic_write(args.out, newline="") as f:
            w = csv.writer(f)
            w.writerow(
                [
                    "heliostat_id",
                    "order",
                    "time_utc",
                    "target",
                    "sun_azimuth_deg",
                    "sun_elevation_deg",
                    "record_id",
                    "uncertainty_after_mrad",
                ]
            )
            for i, hid in enumerate(results.ids):
                for k, c in enumerate(chosen[i]):
                    if c < 0:
                        continue
                    w.writerow(
                        [
                            hid,
                            k + 1,
                            _iso(float(unix_c[i, c])),
                            str(target_of[i, c]),
                            f"{az[i, c]:.4f}",
                            f"{el[i, c]:.4f}",
                            "" if record_ids is None else int(record_ids[i, c]),
                            f"{after[i, k]:.4f}",
                        ]
                    )
        changed = np.zeros(h, bool)
        if "superseded" in results.records:
            changed = np.any(np.asarray(results.records["superseded"], bool), axis=1)
        planned = chosen >= 0  # the uncertainty after the last planned measurement (it only falls)
        final = np.where(planned.any(axis=1), np.min(np.where(planned, after, np.inf), axis=1), before)
        order = np.lexsort((-before, ~changed))  # change points first, then the largest predicted uncertainty
        if args.ranking is not None:
            with atomic_write(args.ranking, newline="") as f:
                w = csv.writer(f)
                w.writerow(
                    [
                        "rank",
                        "heliostat_id",
                        "status",
                        "change_point",
                        "uncertainty_before_mrad",
                        "uncertainty_after_mrad",
                        "n_planned",
                    ]
                )
                for rank, i in enumerate(order, start=1):
                    w.writerow(
                        [
                            rank,
                            results.ids[i],
                            results.status[i],
                            int(changed[i]),
                            f"{before[i]:.4f}",
                            f"{final[i]:.4f}",
                            int((chosen[i] >= 0).sum()),
                        ]
                    )
        if args.records_out is not None and fleet is not None and record_ids is not None:
            later = np.zeros(np.asarray(fleet.mask).shape, bool)
            if args.before is not None:
                later = np.asarray(fleet.mask) & (np.asarray(fleet.context.unix_time) >= args.before.timestamp())
            # From the fit's posterior the plan adds to what the fit knew: its training
            # records train too (without them `calibrate --records` fitted the chosen
            # records alone, and every heliostat the plan gave none to not at all).
            known_train = [np.zeros(0, np.int64) for _ in results.ids]
            if args.start_from == "posterior" and "split" in results.records:
                train_split = np.asarray(results.records["split"]) == SPLIT_CODES["train"]
                rids = np.asarray(results.records["record_id"], np.int64)
                known_train = [rids[i][train_split[i] & np.asarray(results.fitted)[i]] for i in range(len(results.ids))]
            with atomic_write(args.records_out, newline="") as f:
                w = csv.writer(f)
                w.writerow([*RECORDS_HEADER, "role"])
                for i, hid in enumerate(results.ids):
                    r = list(fleet.ids).index(hid) if hid in fleet.ids else -1
                    # records at or after --before are held out, also where the fit trained on
                    # them (a fit of later records: _warn_fitted_after_the_cut said so)
                    held = (
                        set(np.asarray(fleet.record_id)[r][np.asarray(fleet.mask)[r] & ~later[r]].tolist())
                        if r >= 0
                        else set()
                    )
                    planned_ids = [int(record_ids[i, c]) for c in chosen[i][chosen[i] >= 0]]
                    train_ids = [int(x) for x in known_train[i] if int(x) in held and int(x) not in planned_ids]
                    for rid in [*train_ids, *planned_ids]:
                        w.writerow([hid, rid, "train"])
                    if r >= 0:
                        for rid in np.asarray(fleet.record_id)[r][later[r]]:
                            if int(rid) not in train_ids and int(rid) not in planned_ids:
                                w.writerow([hid, int(rid), "test"])
        if args.plot is not None:
            from .._plotting import plot_plan, save_figure

            figure = plot_plan(list(results.ids), before, after, chosen, changed, discrepancy=discrepancy is not None)
            save_figure(figure, args.plot)
    print(
        f"{'rank':>4} {'heliostat':<10} {'change':>6} {'before':>8} {'after':>8}   [mrad, predicted over the envelope]"
    )
    for rank, i in enumerate(order[:10], start=1):
        print(f"{rank:>4} {results.ids[i]:<10} {'yes' if changed[i] else '':>6} {before[i]:8.3f} {final[i]:8.3f}")
    if h > 10:
        print(f"     ... {h - 10} more in --ranking")
    fewest = int(planned.sum(axis=1).min()) if h else args.budget
    short = (  # a window of fewer usable instants than --budget: not the budget's worth, and said so
        f" ({int((planned.sum(axis=1) < args.budget).sum())} heliostat(s) got fewer, as few as {fewest}: "
        + (
            f"they have no more usable records{' before --before' if args.before is not None else ''})"
            if fleet is not None
            else "the window has no more usable instants)"
        )
        if fewest < args.budget
        else ""
    )
    print(
        f"fleet: median predicted pointing uncertainty {np.median(before):.3f} -> {np.median(final):.3f} mrad "
        f"with {args.budget} planned measurement(s) per heliostat{short}"
    )
    print(
        "(predicted: the RMS over the operating envelope of the pointing error that the parameters' uncertainty"
        + (" and the model discrepancy" if discrepancy is not None else "")
        + " leave, without the measurement noise; a held-out error also holds the noise and any drift)"
    )
    return 0
