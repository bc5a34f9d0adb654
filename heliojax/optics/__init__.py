"""Optics: sun shapes, mirror surfaces (ideal, deflectometry, NURBS), flux tracing,
comparison with measured flux images and surface reconstruction."""

from ._compare import (
    CENTRED_WINDOW_M as CENTRED_WINDOW_M,
)
from ._compare import (
    FluxComparison as FluxComparison,
)
from ._compare import (
    compare_record as compare_record,
)
from ._compare import (
    comparison_figure as comparison_figure,
)
from ._compare import (
    default_sunshape as default_sunshape,
)
from ._compare import (
    flux_sample_records as flux_sample_records,
)
from ._compare import (
    geometry_from_properties as geometry_from_properties,
)
from ._compare import (
    layout_from_properties as layout_from_properties,
)
from ._compare import (
    load_flux_png as load_flux_png,
)
from ._compare import (
    normalised_cross_correlation as normalised_cross_correlation,
)
from ._compare import (
    target_from_tower as target_from_tower,
)
from ._flux import (
    ImageGrid as ImageGrid,
)
from ._flux import (
    aim_pose as aim_pose,
)
from ._flux import (
    centroid as centroid,
)
from ._flux import (
    flux_image as flux_image,
)
from ._flux import (
    flux_images as flux_images,
)
from ._flux import (
    pose_from_normal as pose_from_normal,
)
from ._flux import (
    ray_count as ray_count,
)
from ._flux import (
    total_power as total_power,
)
from ._nurbs import (
    NurbsFacets as NurbsFacets,
)
from ._nurbs import (
    bspline_basis as bspline_basis,
)
from ._nurbs import (
    clamped_knots as clamped_knots,
)
from ._nurbs import (
    fit_nurbs as fit_nurbs,
)
from ._nurbs import (
    greville as greville,
)
from ._nurbs import (
    normal_errors_mrad as normal_errors_mrad,
)
from ._nurbs import (
    rms_normal_error_mrad as rms_normal_error_mrad,
)
from ._reconstruct import (
    ReconstructionResult as ReconstructionResult,
)
from ._reconstruct import (
    SyntheticScene as SyntheticScene,
)
from ._reconstruct import (
    flux_loss as flux_loss,
)
from ._reconstruct import (
    normal_rms_error_mrad as normal_rms_error_mrad,
)
from ._reconstruct import (
    reconstruct_surface as reconstruct_surface,
)
from ._reconstruct import (
    synthetic_scene as synthetic_scene,
)
from ._reconstruct import (
    with_height_offsets as with_height_offsets,
)
from ._sunshape import (
    SUN_HALF_ANGLE as SUN_HALF_ANGLE,
)
from ._sunshape import (
    AbstractSunShape as AbstractSunShape,
)
from ._sunshape import (
    BuieSun as BuieSun,
)
from ._sunshape import (
    EffectiveSun as EffectiveSun,
)
from ._sunshape import (
    GaussianSun as GaussianSun,
)
from ._sunshape import (
    PillboxSun as PillboxSun,
)
from ._sunshape import (
    buie_profile as buie_profile,
)
from ._sunshape import (
    offsets_to_directions as offsets_to_directions,
)
from ._sunshape import (
    tangent_basis as tangent_basis,
)
from ._sunshape import (
    uniforms as uniforms,
)
from ._surfaces import (
    Deflectometry as Deflectometry,
)
from ._surfaces import (
    FacetLayout as FacetLayout,
)
from ._surfaces import (
    SurfacePoints as SurfacePoints,
)
from ._surfaces import (
    deflectometry_surface as deflectometry_surface,
)
from ._surfaces import (
    ideal_surface as ideal_surface,
)
from ._surfaces import (
    read_deflectometry as read_deflectometry,
)
from ._surfaces import (
    read_facet_layout as read_facet_layout,
)
from ._surfaces import (
    stack_deflectometry as stack_deflectometry,
)
from ._surfaces import (
    stack_layouts as stack_layouts,
)
from ._surfaces import (
    stack_surfaces as stack_surfaces,
)
from ._surfaces import (
    write_deflectometry as write_deflectometry,
)
