"""Heliostat field acceptance per the SolarPACES heliostat field performance
testing guideline (draft; Röger et al., Solar Energy): sample sizes, level-1
test of means and spreads against the contract, and level 2 (clusters,
resampling advice, KDE extrapolation, field efficiency over a typical year)."""

from ._clusters import (
    ClusterResult as ClusterResult,
)
from ._clusters import (
    SurveyResult as SurveyResult,
)
from ._clusters import (
    adaptive_survey as adaptive_survey,
)
from ._clusters import (
    field_spacing as field_spacing,
)
from ._clusters import (
    find_clusters as find_clusters,
)
from ._clusters import (
    local_std as local_std,
)
from ._clusters import (
    outliers as outliers,
)
from ._clusters import (
    resampling_advice as resampling_advice,
)
from ._clusters import (
    robust_std as robust_std,
)
from ._extrapolate import (
    Extrapolation as Extrapolation,
)
from ._extrapolate import (
    TransformedKDE as TransformedKDE,
)
from ._extrapolate import (
    cv_bandwidth_factor as cv_bandwidth_factor,
)
from ._extrapolate import (
    extrapolate_field as extrapolate_field,
)
from ._extrapolate import (
    fit_kde as fit_kde,
)
from ._field import (
    PARAMETERS as PARAMETERS,
)
from ._field import (
    FieldData as FieldData,
)
from ._field import (
    ParameterInfo as ParameterInfo,
)
from ._field import (
    synthetic_field as synthetic_field,
)
from ._io import (
    Contract as Contract,
)
from ._io import (
    ParameterSpec as ParameterSpec,
)
from ._io import (
    field_from_summary as field_from_summary,
)
from ._io import (
    find_tower_file as find_tower_file,
)
from ._io import (
    load_contract as load_contract,
)
from ._io import (
    positions_from_paint as positions_from_paint,
)
from ._io import (
    read_field_csv as read_field_csv,
)
from ._io import (
    read_positions_csv as read_positions_csv,
)
from ._io import (
    read_summary as read_summary,
)
from ._level1 import (
    Level1Result as Level1Result,
)
from ._level1 import (
    confidence_intervals as confidence_intervals,
)
from ._level1 import (
    level1_test as level1_test,
)
from ._plots import (
    plot_all as plot_all,
)
from ._plots import (
    plot_cluster_distributions as plot_cluster_distributions,
)
from ._plots import (
    plot_field_map as plot_field_map,
)
from ._plots import (
    plot_monthly_efficiency as plot_monthly_efficiency,
)
from ._sampling import (
    sample_size as sample_size,
)
from ._sampling import (
    sample_size_absolute as sample_size_absolute,
)
from ._sampling import (
    select_sample as select_sample,
)
from ._sampling import (
    z_value as z_value,
)
from ._workflow import (
    AcceptanceResult as AcceptanceResult,
)
from ._workflow import (
    contract_values as contract_values,
)
from ._workflow import (
    run_acceptance as run_acceptance,
)
from ._yield import (
    JUELICH_COORDINATES as JUELICH_COORDINATES,
)
from ._yield import (
    SUN_SIGMA_MRAD as SUN_SIGMA_MRAD,
)
from ._yield import (
    SunSeries as SunSeries,
)
from ._yield import (
    YieldResult as YieldResult,
)
from ._yield import (
    atmospheric_attenuation as atmospheric_attenuation,
)
from ._yield import (
    beam_sigma as beam_sigma,
)
from ._yield import (
    clear_sky_dni as clear_sky_dni,
)
from ._yield import (
    cosine_efficiency as cosine_efficiency,
)
from ._yield import (
    field_efficiency as field_efficiency,
)
from ._yield import (
    intercept_efficiency as intercept_efficiency,
)
from ._yield import (
    juelich_receiver as juelich_receiver,
)
from ._yield import (
    load_receiver as load_receiver,
)
from ._yield import (
    typical_year as typical_year,
)
