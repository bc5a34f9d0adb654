"""Heliostat field acceptance per the SolarPACES heliostat field performance
testing guideline (draft; Röger et al., Solar Energy): sample sizes, level-1
test of means and spreads against the contract, and level 2 (clusters,
resampling advice, KDE extrapolation, field efficiency over a typical year)."""

from ._clusters import (
    ClusterResult as ClusterResult,
    SurveyResult as SurveyResult,
    adaptive_survey as adaptive_survey,
    field_spacing as field_spacing,
    find_clusters as find_clusters,
    local_std as local_std,
    outliers as outliers,
    resampling_advice as resampling_advice,
    robust_std as robust_std,
)
from ._extrapolate import (
    Extrapolation as Extrapolation,
    TransformedKDE as TransformedKDE,
    cv_bandwidth_factor as cv_bandwidth_factor,
    extrapolate_field as extrapolate_field,
    fit_kde as fit_kde,
)
from ._field import (
    PARAMETERS as PARAMETERS,
    FieldData as FieldData,
    ParameterInfo as ParameterInfo,
    synthetic_field as synthetic_field,
)
from ._io import (
    Contract as Contract,
    ParameterSpec as ParameterSpec,
    field_from_summary as field_from_summary,
    find_tower_file as find_tower_file,
    load_contract as load_contract,
    positions_from_paint as positions_from_paint,
    read_field_csv as read_field_csv,
    read_positions_csv as read_positions_csv,
    read_summary as read_summary,
)
from ._level1 import (
    Level1Result as Level1Result,
    confidence_intervals as confidence_intervals,
    level1_test as level1_test,
)
from ._plots import (
    plot_all as plot_all,
    plot_cluster_distributions as plot_cluster_distributions,
    plot_field_map as plot_field_map,
    plot_monthly_efficiency as plot_monthly_efficiency,
)
from ._sampling import (
    sample_size as sample_size,
    sample_size_absolute as sample_size_absolute,
    select_sample as select_sample,
    z_value as z_value,
)
from ._workflow import (
    AcceptanceResult as AcceptanceResult,
    contract_values as contract_values,
    run_acceptance as run_acceptance,
)
from ._yield import (
    JUELICH_COORDINATES as JUELICH_COORDINATES,
    SUN_SIGMA_MRAD as SUN_SIGMA_MRAD,
    SunSeries as SunSeries,
    YieldResult as YieldResult,
    atmospheric_attenuation as atmospheric_attenuation,
    beam_sigma as beam_sigma,
    clear_sky_dni as clear_sky_dni,
    cosine_efficiency as cosine_efficiency,
    field_efficiency as field_efficiency,
    intercept_efficiency as intercept_efficiency,
    juelich_receiver as juelich_receiver,
    load_receiver as load_receiver,
    typical_year as typical_year,
)
