"""Discovery: find where the model and the measurements disagree, name the missing
effect, add it, and show the gap shrink.

:func:`discover` runs the workflow on a :class:`heliojax.Fleet` (fit the base
model; screen every candidate effect of :mod:`heliojax.effects` with score
tests orthogonalised against the model's Jacobian; report candidates the model
absorbs as not identifiable; refit the finalists with Levenberg-Marquardt;
name an effect only when it passes Holm's family-wise control, delta BIC > 2
and a blocked-by-day cross-validated held-out improvement; repeat). It starts
from a robust pre-pass (gross errors and change points left out and reported,
:func:`clean`) and ends with residual diagnostics against every recorded
variable (:func:`unexplained_structure`).
:func:`write_report`, :func:`write_markdown` and :func:`write_figures` write
report.json, a Markdown summary and PNG figures; :func:`simulate_fleet` makes
hidden-effect test fleets.
"""

from ._cleaning import (
    Cleaning as Cleaning,
    change_point_pvalues as change_point_pvalues,
    clean as clean,
    confirm_change_points as confirm_change_points,
)
from ._diagnostics import (
    Variable as Variable,
    record_variables as record_variables,
    unexplained_structure as unexplained_structure,
)
from ._identifiability import (
    ABSORBED_LIMIT as ABSORBED_LIMIT,
    CONDITION_INDEX_LIMIT as CONDITION_INDEX_LIMIT,
    absorbed_fractions as absorbed_fractions,
)
from ._lanes import (
    day_folds as day_folds,
    fleet_longitude_deg as fleet_longitude_deg,
    fold_blocks as fold_blocks,
    too_few_days_note as too_few_days_note,
)
from ._report import (
    AMBIGUITY_BIC as AMBIGUITY_BIC,
    MIN_DELTA_BIC as MIN_DELTA_BIC,
    STRONG_EVIDENCE_BIC as STRONG_EVIDENCE_BIC,
    build_report as build_report,
    evidence_grade as evidence_grade,
    markdown_summary as markdown_summary,
    plot_change_points as plot_change_points,
    plot_effect_residuals as plot_effect_residuals,
    plot_heldout_per_step as plot_heldout_per_step,
    plot_screen as plot_screen,
    plot_unexplained as plot_unexplained,
    write_figures as write_figures,
    write_markdown as write_markdown,
    write_report as write_report,
)
from ._screen import CandidateScreen as CandidateScreen, holm as holm
from ._select import (
    DEFAULT_CANDIDATES as DEFAULT_CANDIDATES,
    DiscoveryConfig as DiscoveryConfig,
    DiscoveryResult as DiscoveryResult,
    check_exclusions as check_exclusions,
    discover as discover,
)
from ._suites import random_actuator_models as random_actuator_models, simulate_fleet as simulate_fleet

__all__ = [
    "ABSORBED_LIMIT",
    "AMBIGUITY_BIC",
    "CONDITION_INDEX_LIMIT",
    "CandidateScreen",
    "DEFAULT_CANDIDATES",
    "MIN_DELTA_BIC",
    "STRONG_EVIDENCE_BIC",
    "Cleaning",
    "DiscoveryConfig",
    "DiscoveryResult",
    "check_exclusions",
    "Variable",
    "absorbed_fractions",
    "build_report",
    "change_point_pvalues",
    "clean",
    "confirm_change_points",
    "day_folds",
    "evidence_grade",
    "fleet_longitude_deg",
    "fold_blocks",
    "too_few_days_note",
    "discover",
    "holm",
    "markdown_summary",
    "plot_effect_residuals",
    "plot_heldout_per_step",
    "plot_change_points",
    "plot_screen",
    "plot_unexplained",
    "random_actuator_models",
    "record_variables",
    "simulate_fleet",
    "unexplained_structure",
    "write_figures",
    "write_markdown",
    "write_report",
]
