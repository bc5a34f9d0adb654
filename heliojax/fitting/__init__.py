"""The fit core: one solve function for calibration, discovery and the neural
workflow, with its losses, priors, batching strategies and evaluation."""

from ._batching import (
    AXIS as AXIS,
    BATCHING_NAMES as BATCHING_NAMES,
    MIN_BLOCK as MIN_BLOCK,
    RESTART_AFTER as RESTART_AFTER,
    AbstractBatching as AbstractBatching,
    Chunked as Chunked,
    LaxMap as LaxMap,
    Sharded as Sharded,
    Threaded as Threaded,
    Vmap as Vmap,
    batching_from_name as batching_from_name,
    block_lanes as block_lanes,
    default_batching as default_batching,
    usable_cores as usable_cores,
)
from ._changes import (
    OFFSET_NAMES as OFFSET_NAMES,
    ChangePoints as ChangePoints,
    find_change_points as find_change_points,
)
from ._days import (
    CLUSTERING_ALPHA as CLUSTERING_ALPHA,
    DAY_S as DAY_S,
    DayClustering as DayClustering,
    day_clustering as day_clustering,
    day_labels as day_labels,
    heliostat_noise as heliostat_noise,
)
from ._evaluate import (
    beam_errors_mrad as beam_errors_mrad,
    choose_start_geometry as choose_start_geometry,
    fleet_beam_errors_mrad as fleet_beam_errors_mrad,
    fleet_residuals_mrad as fleet_residuals_mrad,
    residual_jacobians as residual_jacobians,
    residuals_mrad as residuals_mrad,
    typical_actuators as typical_actuators,
)
from ._fit import (
    DEFAULT_ATOL as DEFAULT_ATOL,
    DEFAULT_INITIAL_DAMPING as DEFAULT_INITIAL_DAMPING,
    DEFAULT_MAX_STEPS as DEFAULT_MAX_STEPS,
    DEFAULT_RTOL as DEFAULT_RTOL,
    CompiledFit as CompiledFit,
    FitSolution as FitSolution,
    LeastSquaresOutcome as LeastSquaresOutcome,
    LevenbergMarquardt as LevenbergMarquardt,
    ToleranceTrustRegion as ToleranceTrustRegion,
    default_solver as default_solver,
    fit as fit,
    fit_timed as fit_timed,
    psd_inverse as psd_inverse,
    record_rows as record_rows,
    record_rows_and_jacobian as record_rows_and_jacobian,
    residual_with_jacobian as residual_with_jacobian,
    solve_least_squares as solve_least_squares,
    status_code as status_code,
)
from ._loss import (
    CAUCHY_EFFICIENCY_FACTOR as CAUCHY_EFFICIENCY_FACTOR,
    AbstractLoss as AbstractLoss,
    Cauchy as Cauchy,
    LeastSquares as LeastSquares,
)
from ._pooling import (
    MIN_PRIOR_HELIOSTATS as MIN_PRIOR_HELIOSTATS,
    MIN_RESIDUALS_PER_PARAMETER as MIN_RESIDUALS_PER_PARAMETER,
    flat_prior as flat_prior,
    fleet_prior as fleet_prior,
    prior_moments as prior_moments,
    small_fleet_prior_heliostats as small_fleet_prior_heliostats,
    small_fleet_prior_moments as small_fleet_prior_moments,
    well_determined as well_determined,
)
from ._prior import (
    AbstractPrior as AbstractPrior,
    GaussianPrior as GaussianPrior,
    NoPrior as NoPrior,
    gaussian_prior as gaussian_prior,
)
from ._records import (
    finite_records as finite_records,
    record_residuals_mrad as record_residuals_mrad,
    sanitise as sanitise,
)
from ._robust import (
    NOISE_OUTLIER_MIN_RATIO as NOISE_OUTLIER_MIN_RATIO,
    NOISE_OUTLIER_Z as NOISE_OUTLIER_Z,
    RobustFit as RobustFit,
    fit_robust as fit_robust,
    fitted_start_geometry as fitted_start_geometry,
    noise_outliers as noise_outliers,
    robust_component_noise as robust_component_noise,
    robust_fit_program as robust_fit_program,
    robust_noise as robust_noise,
)
from ._sharding import (
    calibrate_distributed as calibrate_distributed,
    gather_solutions as gather_solutions,
    process_slice as process_slice,
)
from ._status import FitStatus as FitStatus
