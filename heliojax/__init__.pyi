"""Public API of heliojax (the names :mod:`heliojax` loads on first use)."""

from . import (
    acceptance as acceptance,
    discovery as discovery,
    effects as effects,
    fitting as fitting,
    neural as neural,
    optics as optics,
    paint as paint,
)
from ._aim import (
    MAX_SKY_GAP_DEG as MAX_SKY_GAP_DEG,
    AimResult as AimResult,
    aim_fleet as aim_fleet,
    aim_results as aim_results,
    sky_gap_deg as sky_gap_deg,
)
from ._beam import (
    beam_error_components as beam_error_components,
    beam_pointing_error as beam_pointing_error,
    measured_normal as measured_normal,
    reflected_ray as reflected_ray,
    target_miss_distance as target_miss_distance,
)
from ._discrepancy import (
    ModelDiscrepancy as ModelDiscrepancy,
    augment_jacobian as augment_jacobian,
    discrepancy_features as discrepancy_features,
    estimate_discrepancy as estimate_discrepancy,
    inducing_normals as inducing_normals,
    mirror_normals as mirror_normals,
)
from ._errors import ConfigError as ConfigError, DataError as DataError, HeliojaxError as HeliojaxError
from ._fleet import (
    Fleet as Fleet,
    LoadReport as LoadReport,
    bucket_size as bucket_size,
    fleet_from_arrays as fleet_from_arrays,
    fleet_subset as fleet_subset,
    pad_fleet as pad_fleet,
    spots_off_target as spots_off_target,
)
from ._geometry import (
    PlaneHit as PlaneHit,
    TargetPlane as TargetPlane,
    angle_between as angle_between,
    direction_to_azimuth_elevation as direction_to_azimuth_elevation,
    ecef_to_wgs84 as ecef_to_wgs84,
    enu_to_wgs84 as enu_to_wgs84,
    intersect_plane as intersect_plane,
    reflect as reflect,
    sun_direction as sun_direction,
    wgs84_to_ecef as wgs84_to_ecef,
    wgs84_to_enu as wgs84_to_enu,
)
from ._heliostat import (
    HeliostatGeometry as HeliostatGeometry,
    LinearActuators as LinearActuators,
    Pose as Pose,
    RecordContext as RecordContext,
)
from ._kinematics import (
    MODEL_KINDS as MODEL_KINDS,
    AbstractKinematicModel as AbstractKinematicModel,
    AbstractModelWrapper as AbstractModelWrapper,
    ActuatorModel as ActuatorModel,
    StoneModel as StoneModel,
    forward as forward,
    inverse_aim as inverse_aim,
    inverse_normal as inverse_normal,
    nominal_model as nominal_model,
)
from ._parameters import (
    ParameterView as ParameterView,
    broadcast_model as broadcast_model,
    default_free as default_free,
    no_free as no_free,
    parameter as parameter,
    reference as reference,
    set_references as set_references,
)
from ._plan import (
    Candidates as Candidates,
    DiscrepancyDesign as DiscrepancyDesign,
    MeasurementPlan as MeasurementPlan,
    aged_noise_mrad as aged_noise_mrad,
    candidates_at_targets as candidates_at_targets,
    candidates_from_records as candidates_from_records,
    clear_sky_dni as clear_sky_dni,
    discrepancy_design as discrepancy_design,
    discrepancy_from_results as discrepancy_from_results,
    envelope_matrices as envelope_matrices,
    envelope_matrix as envelope_matrix,
    operating_envelope as operating_envelope,
    plan_calibration as plan_calibration,
    plan_measurements as plan_measurements,
    predicted_uncertainty_mrad as predicted_uncertainty_mrad,
    prior_covariance as prior_covariance,
)
from ._plotting import (
    plot_aim as plot_aim,
    plot_calibration as plot_calibration,
    plot_error_per_heliostat as plot_error_per_heliostat,
    plot_plan as plot_plan,
    save_figure as save_figure,
)
from ._predictive import (
    DRIFT_TERMS as DRIFT_TERMS,
    PointingErrorLaw as PointingErrorLaw,
    fit_drift_and_law as fit_drift_and_law,
    fit_drift_and_tails as fit_drift_and_tails,
    fit_drift_gap_and_law as fit_drift_gap_and_law,
    fit_drift_terms_and_law as fit_drift_terms_and_law,
    prediction_region_d2 as prediction_region_d2,
)
from ._programs import clear_caches as clear_caches, memory_map_count as memory_map_count
from ._results import (
    CalibrationResults as CalibrationResults,
    load_results as load_results,
    write_results_h5 as write_results_h5,
)
from ._simulate import (
    approach_directions as approach_directions,
    calibration_target as calibration_target,
    random_stone_models as random_stone_models,
    simulate_records as simulate_records,
    synthetic_contexts as synthetic_contexts,
    synthetic_geometry as synthetic_geometry,
    write_simulation as write_simulation,
)
from ._splits import (
    SPLIT_NAMES as SPLIT_NAMES,
    FleetSplit as FleetSplit,
    SplitResult as SplitResult,
    chronological_holdout as chronological_holdout,
    days_from_fitted_mean as days_from_fitted_mean,
    days_since_fit as days_since_fit,
    record_sky_gap_deg as record_sky_gap_deg,
    split_fleet as split_fleet,
    split_records as split_records,
)
from ._sun import (
    SolarPosition as SolarPosition,
    datetime_to_unix as datetime_to_unix,
    julian_day as julian_day,
    solar_position as solar_position,
)
from ._version import __version__ as __version__
from ._workflow import (
    CalibrationRun as CalibrationRun,
    calibrate as calibrate,
    prediction_d2 as prediction_d2,
    residual_prediction as residual_prediction,
    temporal_drift as temporal_drift,
    write_summary as write_summary,
)
from .discovery import (
    DiscoveryConfig as DiscoveryConfig,
    DiscoveryResult as DiscoveryResult,
    discover as discover,
)
from .effects import (
    EFFECT_NAMES as EFFECT_NAMES,
    EffectModel as EffectModel,
    with_effects as with_effects,
)
from .fitting import (
    AbstractBatching as AbstractBatching,
    AbstractLoss as AbstractLoss,
    AbstractPrior as AbstractPrior,
    Chunked as Chunked,
    FitSolution as FitSolution,
    FitStatus as FitStatus,
    GaussianPrior as GaussianPrior,
    LaxMap as LaxMap,
    LeastSquares as LeastSquares,
    NoPrior as NoPrior,
    Sharded as Sharded,
    Threaded as Threaded,
    Vmap as Vmap,
    beam_errors_mrad as beam_errors_mrad,
    calibrate_distributed as calibrate_distributed,
    choose_start_geometry as choose_start_geometry,
    default_batching as default_batching,
    fit as fit,
    fitted_start_geometry as fitted_start_geometry,
    fleet_beam_errors_mrad as fleet_beam_errors_mrad,
    fleet_residuals_mrad as fleet_residuals_mrad,
    gather_solutions as gather_solutions,
    gaussian_prior as gaussian_prior,
    process_slice as process_slice,
    residual_jacobians as residual_jacobians,
)
from .paint import (
    CalibrationRecord as CalibrationRecord,
    FetchReport as FetchReport,
    HeliostatProperties as HeliostatProperties,
    TowerFile as TowerFile,
    default_data_dir as default_data_dir,
    fetch_catalog as fetch_catalog,
    load_paint_directory as load_paint_directory,
    load_weather_csv_fleet as load_weather_csv_fleet,
    read_calibration_record as read_calibration_record,
    read_heliostat_properties as read_heliostat_properties,
    read_tower as read_tower,
    records_to_fleet as records_to_fleet,
    verify_download as verify_download,
    write_paint_directory as write_paint_directory,
)
