"""Optics: sun shapes, mirror surfaces (ideal, deflectometry, NURBS), flux tracing,
comparison with measured flux images and surface reconstruction."""

from ._artist import (
    Scene as Scene,
    scene_from_artist as scene_from_artist,
    scene_to_artist as scene_to_artist,
)
from ._compare import (
    CENTRED_WINDOW_M as CENTRED_WINDOW_M,
    MAX_UNIFORM_SPREAD as MAX_UNIFORM_SPREAD,
    FluxComparison as FluxComparison,
    FluxRecords as FluxRecords,
    compare_record as compare_record,
    comparison_figure as comparison_figure,
    default_sunshape as default_sunshape,
    flux_records as flux_records,
    flux_sample_records as flux_sample_records,
    geometry_from_properties as geometry_from_properties,
    kl_divergence as kl_divergence,
    layout_from_properties as layout_from_properties,
    load_flux_png as load_flux_png,
    normalised_cross_correlation as normalised_cross_correlation,
    point_at as point_at,
    spot_widths as spot_widths,
    target_from_tower as target_from_tower,
    uniform_spread as uniform_spread,
)
from ._flux import (
    ImageGrid as ImageGrid,
    aim_pose as aim_pose,
    centroid as centroid,
    flux_image as flux_image,
    flux_images as flux_images,
    plane_power as plane_power,
    pose_from_normal as pose_from_normal,
    ray_count as ray_count,
    total_power as total_power,
)
from ._nurbs import (
    NurbsFacets as NurbsFacets,
    bspline_basis as bspline_basis,
    clamped_knots as clamped_knots,
    fit_nurbs as fit_nurbs,
    greville as greville,
    normal_errors_mrad as normal_errors_mrad,
    rms_normal_error_mrad as rms_normal_error_mrad,
)
from ._real import (
    RecordsReconstruction as RecordsReconstruction,
    low_order_shape as low_order_shape,
    normal_deviation_map as normal_deviation_map,
    normal_deviation_mrad as normal_deviation_mrad,
    reconstruct_from_records as reconstruct_from_records,
    records_figure as records_figure,
)
from ._reconstruct import (
    ReconstructionResult as ReconstructionResult,
    SyntheticScene as SyntheticScene,
    flux_loss as flux_loss,
    loss_window as loss_window,
    normal_rms_error_mrad as normal_rms_error_mrad,
    reconstruct_surface as reconstruct_surface,
    synthetic_scene as synthetic_scene,
    with_height_offsets as with_height_offsets,
)
from ._sunshape import (
    SUN_HALF_ANGLE as SUN_HALF_ANGLE,
    AbstractSunShape as AbstractSunShape,
    BuieSun as BuieSun,
    EffectiveSun as EffectiveSun,
    GaussianSun as GaussianSun,
    PillboxSun as PillboxSun,
    buie_profile as buie_profile,
    offsets_to_directions as offsets_to_directions,
    tangent_basis as tangent_basis,
    uniforms as uniforms,
)
from ._surfaces import (
    Deflectometry as Deflectometry,
    FacetLayout as FacetLayout,
    SurfacePoints as SurfacePoints,
    deflectometry_surface as deflectometry_surface,
    ideal_surface as ideal_surface,
    read_deflectometry as read_deflectometry,
    read_facet_layout as read_facet_layout,
    stack_deflectometry as stack_deflectometry,
    stack_layouts as stack_layouts,
    stack_surfaces as stack_surfaces,
    write_deflectometry as write_deflectometry,
)
