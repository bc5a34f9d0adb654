"""``heliojax accept``: field acceptance per the SolarPACES heliostat field
performance testing guideline (sample sizes, level 1, clusters, extrapolation,
level-2 efficiency contract vs measured)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from ._common import path_type, staged_outputs

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  heliojax accept --results field.csv --contract configs/contract.toml --report out/acceptance.json \\
      --figures out/acceptance
  heliojax accept --results out/summary.json --paint ../shared/data/paint --contract configs/contract.toml \\
      --report out/acceptance.json"""

OUTPUT_FILES = ("report",)
OUTPUT_DIRS = ("figures",)
"""Output paths checked before any work (attribute names of the parsed arguments)."""
FIGURES = ("field_map.png", "cluster_distributions.png", "monthly_efficiency.png")
"""The figures ``--figures`` receives (the first two need tracking measured on two heliostats)."""


def outputs_inside(args) -> list[tuple[str, Path]]:
    """The files this command writes in ``--figures``, checked before any work: a
    ``--report figs/field_map.png`` had been written over that figure without a word."""
    return [("figures", Path(args.figures) / name) for name in FIGURES] if args.figures is not None else []


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "accept",
        help="field acceptance test against a contract (SolarPACES guideline)",
        description=(
            "Acceptance analysis of a heliostat field. --results is either a CSV "
            "(heliostat_id,east_m,north_m[,up_m] and any of tracking_mrad,slope_mrad,"
            "reflectance,aperture_m2; empty cell = not measured; every row is a heliostat "
            "of the field) or a fleet-calibration summary.json (tracking error = "
            "test_rms_mrad), which needs the field's positions from --positions or --paint."
        ),
    )
    p.add_argument("--results", required=True, type=path_type, help="measured-field CSV or summary.json")
    p.add_argument("--contract", required=True, type=path_type, help="contract TOML (see configs/contract.toml)")
    p.add_argument("--report", type=path_type, default=Path("acceptance.json"), help="output JSON report")
    p.add_argument("--figures", type=path_type, default=None, help="directory for the three PNG figures")
    p.add_argument(
        "--positions",
        type=path_type,
        default=None,
        help="CSV heliostat_id,east_m,north_m[,up_m] of every heliostat of the field (with a summary.json)",
    )
    p.add_argument(
        "--paint", type=path_type, default=None, help="PAINT download directory: heliostat positions and the tower file"
    )
    p.add_argument(
        "--tower",
        type=path_type,
        default=None,
        help="tower file with the receiver (default: --paint's, else the contract's "
        "[yield] tower_file, else the built-in Jülich receiver)",
    )


def run(args: argparse.Namespace) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from .. import acceptance as acc
    from .._errors import ConfigError, HeliojaxError
    from .._io import staged_folder, write_json

    try:
        contract = acc.load_contract(args.contract)
        if args.results.suffix.lower() == ".json":
            if args.positions is not None:
                # the positions are all --positions' (its frame may not be --paint's: the two are not mixed);
                # --paint still gives the tower file
                ids, pos = acc.read_positions_csv(args.positions)
                source = f"--positions {args.positions}"
                positions = {"positions": str(args.positions), "positions_from": "--positions"}
                if args.paint is not None:
                    source += ", which takes precedence over --paint,"
                    positions["positions_from"] = "--positions (the heliostat positions of --paint not used)"
                    log.warning(
                        f"--positions {args.positions} given: the heliostat positions of --paint {args.paint} are "
                        "not used (--paint gives the tower file only)"
                    )
            elif args.paint is not None:
                ids, pos = acc.positions_from_paint(args.paint)
                source = f"--paint {args.paint}"
                positions = {"positions": str(args.paint), "positions_from": "--paint (heliostat properties files)"}
            else:
                raise ConfigError("a summary.json needs the heliostat positions: give --positions or --paint")
            field = acc.field_from_summary(args.results, ids, pos, positions_from=source)
            positions_file = args.positions if args.positions is not None else args.paint
        else:
            if args.positions is not None:
                raise ConfigError(
                    f"--positions {args.positions}: only read with a summary.json --results "
                    f"(the CSV {args.results.name} carries the positions)"
                )
            field = acc.read_field_csv(args.results)
            positions = {"positions": str(args.results), "positions_from": "--results (the field CSV)"}
            positions_file = args.results
        tower = args.tower
        if tower is None and args.paint is not None:
            tower = acc.find_tower_file(args.paint)
        if tower is None and contract.tower_file is not None and contract.tower_file.exists():
            tower = contract.tower_file
        if tower is not None:
            aperture, plant = acc.load_receiver(tower)
            receiver_source = str(tower)
        else:
            aperture, plant = acc.juelich_receiver(), acc.JUELICH_COORDINATES
            receiver_source = "built-in Jülich receiver"
        # a heliostat at the tower's foot (positions in km?) is a warning of run_acceptance; the spacing
        # of the heliostats is checked (and refused) where they are read
        result = acc.run_acceptance(field, contract, aperture, plant, positions_source=str(positions_file))
        report = dict(result.report)
        report["inputs"] = {
            "results": str(args.results),
            "contract": str(args.contract),
            "receiver": receiver_source,
            **positions,
        }
        # the report and its figures are published together (a run stopped while drawing
        # leaves the previous set), and a figure this run does not draw is not left from
        # an earlier run beside the new report
        with staged_outputs(args, ("report",)):
            write_json(args.report, report)
            if args.figures is not None:
                drawn = {p.name for p in staged_folder(args.figures, lambda d: acc.plot_all(result, d))}
                for stale in sorted(set(FIGURES) - drawn):
                    (args.figures / stale).unlink(missing_ok=True)
                if "field_map.png" not in drawn:
                    log.warning(
                        "field_map.png and cluster_distributions.png not drawn (an earlier run's removed): they "
                        "need tracking_mrad measured on at least 2 heliostats"
                    )
    except HeliojaxError as e:
        print(f"heliojax accept: error: {e}", file=sys.stderr)
        return 2
    l2 = report["level2"]
    for name, r in report["level1"].items():
        if r["pass"] is None:
            status = "n/a"
        elif not (r["pass_mean"] and r["pass_std"]):
            why = [  # which of the two the contract's value lies outside (the reason was in the JSON only)
                f"{what} {r[what]:.3g} ({r[f'{what}_ci'][0]:.3g}..{r[f'{what}_ci'][1]:.3g}) against the "
                f"contract's {r[f'contract_{what}']:.3g}"
                for what in ("mean", "std")
                if not r[f"pass_{what}"] and r.get(f"{what}_ci") is not None
            ]
            status = "FAIL" + (f": {'; '.join(why)}" if why else "")
        else:  # mean and std consistent with the contract: passed unless the sample is too small
            status = "pass" if r["pass"] else "too few heliostats"
        print(f"{name:14s} n={r.get('n')}/{report['sample_sizes'][name]}  {status}")
    if l2["annual_efficiency_measured"] is None:
        print(
            f"annual efficiency: contract {l2['annual_efficiency_contract']:.4f}, measured: not assessed "
            f"({l2['not_assessed_reason']})"
        )
    else:
        assumed = l2["parameters_from_contract"]
        note = f" (contract's values assumed for {', '.join(assumed)}: not measured)" if assumed else ""
        print(
            f"annual efficiency: contract {l2['annual_efficiency_contract']:.4f}, "
            f"measured {l2['annual_efficiency_measured']:.4f}{note}"
        )
    print(f"verdict: {report['verdict']}")
    return 0
