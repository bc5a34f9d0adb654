"""heliojax: a JAX-based, purely functional digital twin of a heliostat field.

Conventions (ENU metres, radians inside, PAINT azimuth 0 = south positive east)
are written down once, in :mod:`heliojax._geometry`. Precision-critical code
(geodesy, calibration) needs float64: call
``jax.config.update("jax_enable_x64", True)`` before use (the CLI does; the
library never flips global flags at import).
"""

from __future__ import annotations

from . import acceptance as acceptance  # noqa: E402
from . import discovery as discovery  # noqa: E402
from . import effects as effects
from . import neural as neural
from . import optics as optics
from . import paint as paint
from ._aim import AimResult as AimResult
from ._aim import aim_fleet as aim_fleet
from ._aim import aim_results as aim_results
from ._errors import ConfigError as ConfigError
from ._errors import DataError as DataError
from ._errors import HeliojaxError as HeliojaxError
from ._fleet import (
    Fleet as Fleet,
)
from ._fleet import (
    LoadReport as LoadReport,
)
from ._fleet import (
    bucket_size as bucket_size,
)
from ._fleet import (
    fleet_from_arrays as fleet_from_arrays,
)
from ._fleet import (
    fleet_subset as fleet_subset,
)
from ._fleet import (
    pad_fleet as pad_fleet,
)
from ._geometry import (
    PlaneHit as PlaneHit,
)
from ._geometry import (
    TargetPlane as TargetPlane,
)
from ._geometry import (
    angle_between as angle_between,
)
from ._geometry import (
    direction_to_azimuth_elevation as direction_to_azimuth_elevation,
)
from ._geometry import (
    ecef_to_wgs84 as ecef_to_wgs84,
)
from ._geometry import (
    enu_to_wgs84 as enu_to_wgs84,
)
from ._geometry import (
    intersect_plane as intersect_plane,
)
from ._geometry import (
    reflect as reflect,
)
from ._geometry import (
    sun_direction as sun_direction,
)
from ._geometry import (
    wgs84_to_ecef as wgs84_to_ecef,
)
from ._geometry import (
    wgs84_to_enu as wgs84_to_enu,
)
from ._kinematics import (
    MODEL_KINDS as MODEL_KINDS,
)
from ._kinematics import (
    AbstractKinematicModel as AbstractKinematicModel,
)
from ._kinematics import (
    AbstractModelWrapper as AbstractModelWrapper,
)
from ._kinematics import (
    ActuatorModel as ActuatorModel,
)
from ._kinematics import (
    HeliostatGeometry as HeliostatGeometry,
)
from ._kinematics import (
    LinearActuators as LinearActuators,
)
from ._kinematics import (
    Pose as Pose,
)
from ._kinematics import (
    RecordContext as RecordContext,
)
from ._kinematics import (
    StoneModel as StoneModel,
)
from ._kinematics import (
    beam_error_components as beam_error_components,
)
from ._kinematics import (
    beam_pointing_error as beam_pointing_error,
)
from ._kinematics import (
    forward as forward,
)
from ._kinematics import (
    inverse_aim as inverse_aim,
)
from ._kinematics import (
    inverse_normal as inverse_normal,
)
from ._kinematics import (
    measured_normal as measured_normal,
)
from ._kinematics import (
    nominal_model as nominal_model,
)
from ._kinematics import (
    reflected_ray as reflected_ray,
)
from ._kinematics import (
    target_miss_distance as target_miss_distance,
)
from ._parameters import (
    ParameterView as ParameterView,
)
from ._parameters import (
    broadcast_model as broadcast_model,
)
from ._parameters import (
    default_free as default_free,
)
from ._parameters import (
    no_free as no_free,
)
from ._parameters import (
    parameter as parameter,
)
from ._parameters import (
    reference as reference,
)
from ._parameters import (
    set_references as set_references,
)
from ._results import (
    CalibrationResults as CalibrationResults,
)
from ._results import (
    load_results as load_results,
)
from ._results import (
    write_results_h5 as write_results_h5,
)
from ._simulate import (
    approach_directions as approach_directions,
)
from ._simulate import (
    calibration_target as calibration_target,
)
from ._simulate import (
    random_stone_models as random_stone_models,
)
from ._simulate import (
    simulate_records as simulate_records,
)
from ._simulate import (
    synthetic_contexts as synthetic_contexts,
)
from ._simulate import (
    synthetic_geometry as synthetic_geometry,
)
from ._simulate import (
    write_simulation as write_simulation,
)
from ._splits import (
    SPLIT_NAMES as SPLIT_NAMES,
)
from ._splits import (
    FleetSplit as FleetSplit,
)
from ._splits import (
    SplitResult as SplitResult,
)
from ._splits import (
    split_fleet as split_fleet,
)
from ._splits import (
    split_records as split_records,
)
from ._sun import (
    SolarPosition as SolarPosition,
)
from ._sun import (
    datetime_to_unix as datetime_to_unix,
)
from ._sun import (
    julian_day as julian_day,
)
from ._sun import (
    solar_position as solar_position,
)
from ._version import __version__ as __version__
from ._workflow import (
    CalibrationRun as CalibrationRun,
)
from ._workflow import (
    calibrate as calibrate,
)
from ._workflow import (
    write_summary as write_summary,
)
from .discovery import (  # noqa: E402
    DiscoveryConfig as DiscoveryConfig,
)
from .discovery import (
    DiscoveryResult as DiscoveryResult,
)
from .discovery import (
    discover as discover,
)
from .effects import (  # noqa: E402
    EFFECT_NAMES as EFFECT_NAMES,
)
from .effects import (
    EffectModel as EffectModel,
)
from .effects import (
    with_effects as with_effects,
)
from .fitting import (
    AbstractBatching as AbstractBatching,
)
from .fitting import (
    AbstractLoss as AbstractLoss,
)
from .fitting import (
    AbstractPrior as AbstractPrior,
)
from .fitting import (
    Chunked as Chunked,
)
from .fitting import (
    FitSolution as FitSolution,
)
from .fitting import (
    FitStatus as FitStatus,
)
from .fitting import (
    GaussianPrior as GaussianPrior,
)
from .fitting import (
    LaxMap as LaxMap,
)
from .fitting import (
    LeastSquares as LeastSquares,
)
from .fitting import (
    NoPrior as NoPrior,
)
from .fitting import (
    Sharded as Sharded,
)
from .fitting import (
    Vmap as Vmap,
)
from .fitting import (
    beam_errors_mrad as beam_errors_mrad,
)
from .fitting import (
    calibrate_distributed as calibrate_distributed,
)
from .fitting import (
    choose_start_geometry as choose_start_geometry,
)
from .fitting import (
    default_batching as default_batching,
)
from .fitting import (
    fit as fit,
)
from .fitting import (
    fleet_beam_errors_mrad as fleet_beam_errors_mrad,
)
from .fitting import (
    fleet_residuals_mrad as fleet_residuals_mrad,
)
from .fitting import (
    gather_solutions as gather_solutions,
)
from .fitting import (
    gaussian_prior as gaussian_prior,
)
from .fitting import (
    process_slice as process_slice,
)
from .paint import (
    CalibrationRecord as CalibrationRecord,
)
from .paint import (
    FetchReport as FetchReport,
)
from .paint import (
    HeliostatProperties as HeliostatProperties,
)
from .paint import (
    TowerFile as TowerFile,
)
from .paint import (
    default_data_dir as default_data_dir,
)
from .paint import (
    fetch_catalog as fetch_catalog,
)
from .paint import (
    load_paint_directory as load_paint_directory,
)
from .paint import (
    load_weather_csv_fleet as load_weather_csv_fleet,
)
from .paint import (
    read_calibration_record as read_calibration_record,
)
from .paint import (
    read_heliostat_properties as read_heliostat_properties,
)
from .paint import (
    read_tower as read_tower,
)
from .paint import (
    records_to_fleet as records_to_fleet,
)
from .paint import (
    verify_download as verify_download,
)
from .paint import (
    write_paint_directory as write_paint_directory,
)
