"""Ablation options shared by the coverage benchmarks (``pooled_coverage.py``,
``predictive_coverage.py``): the predictive law's validation origins."""

from __future__ import annotations

import argparse

from heliojax.cli._common import number


def add_holdout_fractions(parser: argparse.ArgumentParser) -> None:
    """``--holdout-fractions F [F ...]``: the predictive law's validation origins."""
    parser.add_argument(
        "--holdout-fractions",
        type=number(0.0, 1.0, above=True, below=True),
        nargs="+",
        default=None,
        metavar="F",
        help="ablation: the predictive law's validation origins (default: heliojax's DRIFT_HOLDOUT_FRACTIONS; "
        "0.3 alone as before 2026-12-06, tenth session)",
    )


def apply_holdout_fractions(args: argparse.Namespace) -> None:
    """Set heliojax's validation origins to ``args.holdout_fractions`` (given)."""
    if args.holdout_fractions is not None:
        from heliojax import _workflow

        _workflow.DRIFT_HOLDOUT_FRACTIONS = tuple(args.holdout_fractions)  # read by temporal_drift at each call
