"""The fit core: one solve function for calibration, discovery and the neural
workflow, with its losses, priors, batching strategies and evaluation."""

from ._batching import (
    AXIS as AXIS,
)
from ._batching import (
    BATCHING_NAMES as BATCHING_NAMES,
)
from ._batching import (
    AbstractBatching as AbstractBatching,
)
from ._batching import (
    Chunked as Chunked,
)
from ._batching import (
    LaxMap as LaxMap,
)
from ._batching import (
    Sharded as Sharded,
)
from ._batching import (
    Vmap as Vmap,
)
from ._batching import (
    batching_from_name as batching_from_name,
)
from ._batching import (
    default_batching as default_batching,
)
from ._evaluate import (
    beam_errors_mrad as beam_errors_mrad,
)
from ._evaluate import (
    choose_start_geometry as choose_start_geometry,
)
from ._evaluate import (
    fleet_beam_errors_mrad as fleet_beam_errors_mrad,
)
from ._evaluate import (
    fleet_residuals_mrad as fleet_residuals_mrad,
)
from ._evaluate import (
    residuals_mrad as residuals_mrad,
)
from ._evaluate import (
    typical_actuators as typical_actuators,
)
from ._fit import (
    DEFAULT_ATOL as DEFAULT_ATOL,
)
from ._fit import (
    DEFAULT_MAX_STEPS as DEFAULT_MAX_STEPS,
)
from ._fit import (
    DEFAULT_RTOL as DEFAULT_RTOL,
)
from ._fit import (
    CompiledFit as CompiledFit,
)
from ._fit import (
    FitSolution as FitSolution,
)
from ._fit import (
    LeastSquaresOutcome as LeastSquaresOutcome,
)
from ._fit import (
    default_solver as default_solver,
)
from ._fit import (
    fit as fit,
)
from ._fit import (
    fit_timed as fit_timed,
)
from ._fit import (
    psd_inverse as psd_inverse,
)
from ._fit import (
    solve_least_squares as solve_least_squares,
)
from ._fit import (
    status_code as status_code,
)
from ._loss import (
    CAUCHY_EFFICIENCY_FACTOR as CAUCHY_EFFICIENCY_FACTOR,
)
from ._loss import (
    AbstractLoss as AbstractLoss,
)
from ._loss import (
    Cauchy as Cauchy,
)
from ._loss import (
    LeastSquares as LeastSquares,
)
from ._prior import (
    AbstractPrior as AbstractPrior,
)
from ._prior import (
    GaussianPrior as GaussianPrior,
)
from ._prior import (
    NoPrior as NoPrior,
)
from ._prior import (
    gaussian_prior as gaussian_prior,
)
from ._records import (
    finite_records as finite_records,
)
from ._records import (
    record_residuals_mrad as record_residuals_mrad,
)
from ._records import (
    sanitise as sanitise,
)
from ._robust import (
    RobustFit as RobustFit,
)
from ._robust import (
    fit_robust as fit_robust,
)
from ._robust import (
    robust_noise as robust_noise,
)
from ._sharding import (
    calibrate_distributed as calibrate_distributed,
)
from ._sharding import (
    gather_solutions as gather_solutions,
)
from ._sharding import (
    process_slice as process_slice,
)
from ._status import FitStatus as FitStatus
