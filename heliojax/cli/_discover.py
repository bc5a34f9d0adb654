"""``heliojax discover``: name the effects the base model misses (thin over
:func:`heliojax.discovery.discover`)."""

from __future__ import annotations

import logging
from pathlib import Path

from .._limits import MAX_FOLDS
from ._common import (
    add_data_argument,
    add_fit_arguments,
    enable_compilation_cache,
    integer,
    load_fleet,
    number,
    path_type,
    staged_outputs,
)

BASES = ("auto", "actuator", "stone8")

log = logging.getLogger(__name__)


EFFECT_CHOICES = tuple(
    "actuator_geometry backlash thermal wind clock gravity_sag encoder_wobble refraction "
    "survey_heliostat survey_target offset_drift".split()
)
"""``heliojax.effects.EFFECT_NAMES`` (kept here so that ``--help`` needs no JAX; a
test checks they agree)."""
EXAMPLES = """examples:
  heliojax discover --base actuator --report out/report.json --figures out/discovery
  heliojax discover ../shared/data/paint --base actuator --effects thermal,backlash --markdown out/discovery.md"""

OUTPUT_FILES = ("report", "markdown")
OUTPUT_DIRS = ("figures", "cache_dir")
"""Output paths checked before any work (attribute names of the parsed arguments)."""


def outputs_inside(args) -> list[tuple[str, Path]]:
    """``--report`` / ``--markdown`` where a figure of ``--figures`` may be written
    (a name of :data:`heliojax.discovery._report.FIGURE_NAME_PATTERN` in that folder),
    checked before any work as a file of ``--figures``, which names the clash:
    ``--report figs/heldout_per_step.png --figures figs`` had been replaced by the figure."""
    from ..discovery._report import FIGURE_NAME_PATTERN

    if args.figures is None:
        return []
    folder = Path(args.figures).resolve()
    return [
        ("figures", Path(args.figures) / Path(value).name)
        for value in (args.report, args.markdown)
        if value is not None
        and Path(value).resolve().parent == folder
        and FIGURE_NAME_PATTERN.fullmatch(Path(value).name)
    ]


def excluded_ids(exclude: str | None) -> tuple[str, ...]:
    """The heliostat ids of ``--exclude`` (comma-separated; None: none). ConfigError when
    the option names none."""
    from .._errors import ConfigError

    if exclude is None:
        return ()
    ids = tuple(dict.fromkeys(i.strip() for i in exclude.split(",") if i.strip()))
    if not ids:
        raise ConfigError(f"--exclude {exclude!r}: no heliostat id given")
    return ids


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "discover",
        help="find where the model and the measurements disagree and name the missing effects",
        description=(
            "Fit the base model robustly (gross errors left out and reported; change points - jumps of the "
            "axis offsets - reported and fitted as jumps of the joint zeros), screen the candidate effects ("
            + ", ".join(EFFECT_CHOICES)
            + ") with score tests on the residuals (largely absorbed ones on their remainder), refit every "
            "significant one and name an effect only when it passes Holm's family-wise control, "
            "delta BIC > 2 and a blocked-by-day cross-validated held-out improvement; repeat. Then test the "
            "residuals against every recorded variable and report structure no library effect explains. "
            "Writes report.json, PNG figures and optionally a Markdown summary."
        ),
    )
    add_data_argument(p)
    p.add_argument(
        "--base",
        choices=BASES,
        default="auto",
        help="base kinematic model: auto = the actuator model following each heliostat's declared actuators "
        "(linear or ideal), stone8 = linear counts-to-angle map",
    )
    p.add_argument("--report", type=path_type, default=Path("report.json"), metavar="FILE", help="report.json path")
    p.add_argument(
        "--figures", type=path_type, default=None, metavar="DIR", help="directory for the PNG figures (default: none)"
    )
    p.add_argument("--markdown", type=path_type, default=None, metavar="FILE", help="Markdown summary file")
    p.add_argument(
        "--effects",
        default=None,
        metavar="NAMES",
        help="comma-separated candidate effects (default: every library effect)",
    )
    p.add_argument(
        "--alpha",
        type=number(0.0, 1.0, above=True, below=True),
        default=0.01,
        help="family-wise error rate per step (Holm), between 0 and 1",
    )
    p.add_argument(
        "--folds", type=integer(2, MAX_FOLDS), default=5, help="blocked cross-validation folds (by local day)"
    )
    p.add_argument("--max-named", type=integer(1), default=6, help="most effects to name (>= 1)")
    p.add_argument(
        "--no-robust", action="store_true", help="keep every record (no gross-error flags; default: robust pre-pass)"
    )
    p.add_argument("--no-changes", action="store_true", help="no change-point scan (default: scan and report)")
    p.add_argument(
        "--no-effect-prior",
        action="store_true",
        help="refit per-heliostat effect parameters without the prior of their typical size (default: with it)",
    )
    p.add_argument(
        "--no-generic-competitors",
        action="store_true",
        help="name library effects without letting generic functions of the time of day and the wind vector "
        "compete (default: they compete; one that wins is reported unexplained)",
    )
    p.add_argument(
        "--exclude",
        default=None,
        metavar="IDS",
        help="comma-separated heliostat ids to leave out (default: none)",
    )
    p.add_argument(
        "--keep-noisy",
        action="store_true",
        help="keep heliostats whose noise after the robust pre-pass lies far above the fleet's (default: left out "
        "after it, as calibrate leaves them out of its fleet statistics; the report's noisy_heliostats names them)",
    )
    add_fit_arguments(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar or messages on stderr")


def run(args) -> int:
    import numpy as np

    from .._errors import ConfigError
    from .._io import staged_folder
    from .._progress import activity
    from ..discovery import (
        DiscoveryConfig,
        check_exclusions,
        discover,
        fleet_longitude_deg,
        fold_blocks,
        markdown_summary,
        too_few_days_note,
        write_figures,
        write_markdown,
        write_report,
    )
    from ..effects import EFFECT_NAMES

    enable_compilation_cache(args.cache_dir, args.command)
    effects = None
    if args.effects is not None:
        effects = tuple(e.strip() for e in args.effects.split(",") if e.strip())
        if not effects:
            raise ConfigError(
                f"--effects {args.effects!r}: no effect named; expected names from {', '.join(EFFECT_NAMES)}"
            )
        unknown = sorted(set(effects) - set(EFFECT_NAMES))
        if unknown:
            raise ConfigError(f"--effects: unknown effects {unknown}; expected names from {', '.join(EFFECT_NAMES)}")
        twice = sorted({e for e in effects if effects.count(e) > 1})
        if twice:
            raise ConfigError(f"--effects: {', '.join(twice)} named twice")
    try:
        config = DiscoveryConfig(
            base=args.base,
            effects=effects,
            alpha=args.alpha,
            n_folds=args.folds,
            max_named=args.max_named,
            start=args.start,
            robust=not args.no_robust,
            changes=not args.no_changes,
            effect_prior=not args.no_effect_prior,
            generic_competitors=not args.no_generic_competitors,
            keep_noisy=args.keep_noisy,
            exclude=excluded_ids(args.exclude),
        )
    except ValueError as e:
        raise ConfigError(str(e)) from e
    fleet = load_fleet(args)
    try:
        check_exclusions(fleet.ids, config.exclude)
    except ValueError as e:
        raise ConfigError(f"--{e}") from None
    blocks = fold_blocks(np.asarray(fleet.context.unix_time), np.asarray(fleet.mask), fleet_longitude_deg(fleet))
    if 2 <= blocks < args.folds:  # (fewer than 2: discover says nothing can be tested)
        raise ConfigError(
            f"--folds {args.folds}: the records span only {blocks} days (a record without a time counts as "
            f"one), so some folds would hold no record; at most --folds {blocks}"
        )
    note = too_few_days_note(blocks)
    if note is not None and np.asarray(fleet.mask).any():
        log.warning(note)
    result = discover(fleet, config)
    # the report, its markdown and the figures are published together: a run stopped
    # while drawing leaves the previous ones as they were
    with staged_outputs(args, ("report", "markdown")):
        write_report(args.report, result.report)
        if args.markdown is not None:
            write_markdown(args.markdown, result.report)
        if args.figures is not None:
            with activity("drawing the figures", logger=log):
                paths = staged_folder(args.figures, lambda folder: write_figures(result, folder))
    if args.figures is not None:
        log.info(f"wrote {len(paths)} figures to {args.figures}")  # pyright: ignore[reportPossiblyUnboundVariable]
    if result.report.get("not_tested_reason"):
        log.warning(f"nothing tested: {result.report['not_tested_reason']}")
    print(markdown_summary(result.report))
    return 0
