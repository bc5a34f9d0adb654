"""Validation of traced flux against PAINT's measured flux images.

PAINT ships, per calibration record, two 256 x 256 grey-scale PNGs of the spot
on the calibration target (camera images rectified onto the target plane):

* ``<ID>-flux.png`` covers the **whole target rectangle** (its width and height
  from the tower file's corners), column 0 at the target's "left" edge (east
  for the north-facing Jülich targets) and row 0 at the top. (This is how
  ARTIST reads them: ``bitmap_coordinates_to_target_coordinates`` maps pixel
  centres linearly onto the target's width and height.) Pixels are therefore not
  square (e.g. 8.6 m x 7.2 m for ``solar_tower_juelich_upper``).
* ``<ID>-flux-centered.png`` is a **6 m x 6 m** window centred on the spot's
  centre of mass (ARTIST's ``utis_crop_width`` / ``utis_crop_height``, used by
  its ``crop_flux_distributions_around_center`` to compare predictions with
  these images).

Brightness is relative (8-bit, normalised per image), so only shapes and
positions are compared: the centroid distance in metres on the target plane and
the normalised cross-correlation (Pearson correlation of the pixel values) of
the images. The mapping of the PNG onto the target is checked against the
record's own focal-spot centroid (``focal_spot.UTIS``/``HeliOS``):
:attr:`FluxComparison.png_vs_record_m`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import typing
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._errors import DataError
from .._geometry import TargetPlane, bisector_normal, normalize, sun_direction, wgs84_to_enu
from .._heliostat import HeliostatGeometry, LinearActuators, Pose
from .._kinematics import AbstractKinematicModel, ActuatorModel, forward
from .._plotting import pyplot
from .._progress import progress_bar
from ..paint import read_calibration_record, read_flux_png, read_heliostat_properties, read_tower
from ..paint._common import MAX_HELIOSTAT_DISTANCE_M
from ..paint._tower import check_target_corners
from ._flux import ImageGrid, centroid, flux_image
from ._sunshape import AbstractSunShape, BuieSun, EffectiveSun
from ._surfaces import FacetLayout, SurfacePoints, ideal_surface

log = logging.getLogger(__name__)

load_flux_png = read_flux_png
"""Alias of :func:`heliojax.paint.read_flux_png`."""

CENTRED_WINDOW_M = (6.0, 6.0)
"""Width and height (m) of PAINT's ``-flux-centered`` images."""


def remove_background(image: np.ndarray) -> np.ndarray:
    """Subtract the median of the one-pixel border and clip at 0."""
    border = np.concatenate([image[0], image[-1], image[:, 0], image[:, -1]])
    return np.clip(image - np.median(border), 0.0, None)


def normalised_cross_correlation(a, b) -> float:
    """Pearson correlation of two equally shaped images (1 = identical up to scale/offset)."""
    a = np.asarray(a, np.float64).ravel()
    b = np.asarray(b, np.float64).ravel()
    a = a - a.mean()
    b = b - b.mean()
    den = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / den) if den > 0 else float("nan")


def kl_divergence(measured, traced, floor: float = 1e-9) -> float:
    """Kullback-Leibler divergence ``KL(p || q) = sum p ln(p / q)`` (nats) of the
    measured image ``p`` from the traced ``q``, both normalised to unit sum after a
    floor of ``floor`` per pixel (so a pixel that the Monte Carlo trace left empty
    costs a finite amount); 0 for identical shapes, independent of brightness."""
    p = np.asarray(measured, np.float64).ravel()
    q = np.asarray(traced, np.float64).ravel()
    p = np.clip(p, 0.0, None) / max(p.clip(0.0).sum(), 1e-300) + floor
    q = np.clip(q, 0.0, None) / max(q.clip(0.0).sum(), 1e-300) + floor
    p, q = p / p.sum(), q / q.sum()
    return float(np.sum(p * np.log(p / q)))


def spot_widths(image: np.ndarray, grid: ImageGrid) -> np.ndarray:
    """Second-moment widths ``(sigma_u, sigma_v)`` in m of a (background-free) image
    on ``grid``: the standard deviations of the brightness along both target axes."""
    img = np.clip(np.asarray(image, np.float64), 0.0, None)
    u, v = (np.asarray(x, np.float64) for x in grid.pixel_centres())
    total = max(img.sum(), 1e-300)
    cu = (img * u[None, :]).sum() / total
    cv = (img * v[:, None]).sum() / total
    su = np.sqrt((img * (u[None, :] - cu) ** 2).sum() / total)
    sv = np.sqrt((img * (v[:, None] - cv) ** 2).sum() / total)
    return np.asarray([su, sv])


def point_at(pose: Pose, sun, spot) -> Pose:
    """``pose`` turned by the smallest rotation that sends the central sun ray's
    reflection from the mirror centre to ``spot`` (ENU m): the kinematic pose with
    its pointing error removed (the rotation about the normal is kept)."""
    want = bisector_normal(sun, normalize(jnp.asarray(spot, pose.centre.dtype) - pose.centre))
    n = pose.normal
    v = jnp.cross(n, want)
    c = jnp.dot(n, want)
    k = jnp.asarray([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], n.dtype)
    turn = jnp.eye(3, dtype=n.dtype) + k + k @ k / (1.0 + c)
    return Pose(normal=want, centre=pose.centre, rotation=turn @ pose.rotation)


def image_centroid(image: np.ndarray, grid: ImageGrid) -> np.ndarray:
    """Centroid ``(u, v)`` in m of a (background-free) image on ``grid``."""
    return np.asarray(_centroid(jnp.asarray(image, jnp.float64), grid), np.float64)


_centroid = eqx.filter_jit(centroid)
"""Compiled :func:`heliojax.optics.centroid` (one program per image shape, not an eager op-by-op call)."""


def measured_images(record_path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """A record's ``-flux.png`` and ``-flux-centered.png`` (same folder, same ID),
    background removed (:func:`remove_background`), relative brightness."""
    record_path = Path(record_path)
    stem = record_path.name.replace("-calibration-properties.json", "")
    images = []
    for kind in ("flux", "flux-centered"):
        path = record_path.parent / f"{stem}-{kind}.png"
        image = load_flux_png(path)
        if min(image.shape) < MIN_FLUX_PIXELS:
            raise DataError(path, None, f"image of {image.shape[1]} x {image.shape[0]} pixels: too small for a spot")
        if image.shape[0] != image.shape[1]:
            # PAINT's are square; a cropped one is still mapped onto the whole target (or a
            # 6 m window), so every position read from it is off (2 m for 256 x 10 pixels)
            log.warning(
                f"{path}: {image.shape[1]} x {image.shape[0]} pixels, not square like PAINT's flux images "
                "(256 or 512 a side): cropped? It is read as covering the whole "
                f"{'target' if kind == 'flux' else 'centred window'}, so the comparison's positions are not "
                "to be trusted"
            )
        image = remove_background(image)
        if not image.any():
            raise DataError(path, None, "no flux spot: the image is uniform after removing its border's level")
        spread = uniform_spread(image)
        if spread > MAX_UNIFORM_SPREAD:
            raise DataError(
                path,
                None,
                f"no flux spot: its brightness is spread over the whole image like noise (second-moment widths "
                f"at least {spread:.2f} of a uniformly lit image's along both axes; a spot's are at most "
                f"{MAX_UNIFORM_SPREAD})",
            )
        images.append(image)
    return images[0], images[1]


MIN_FLUX_PIXELS = 8
"""Fewest pixels per side of a measured flux image (PAINT's are 256 or 512)."""


MAX_UNIFORM_SPREAD = 0.8
"""Largest :func:`uniform_spread` of a measured flux image: a spot is concentrated on
the target, and an image whose brightness is spread like that of a uniformly lit
image (1.0; pure noise after :func:`remove_background` gives 1.0 too) holds no spot
to compare with. The shared real flux images lie at 0.31-0.58."""


def uniform_spread(image: np.ndarray) -> float:
    """The smaller of a (background-free) image's two second-moment widths along its
    rows and columns, each divided by that of a uniformly lit image of the same size
    (its side over ``sqrt(12)``), both in pixels: ~0.1-0.6 for a spot, 1 for uniform
    light or noise."""
    rows, cols = np.shape(image)
    pixels = ImageGrid(  # one metre per pixel
        u_min=jnp.asarray(0.0),
        u_max=jnp.asarray(float(cols)),
        v_min=jnp.asarray(0.0),
        v_max=jnp.asarray(float(rows)),
        shape=(rows, cols),
    )
    widths = spot_widths(image, pixels) / (np.asarray([cols, rows], np.float64) / np.sqrt(12.0))
    return float(min(widths))


def geometry_from_properties(properties, origin_lla) -> HeliostatGeometry:
    """:class:`HeliostatGeometry` (float64, ENU m) of a
    :class:`heliojax.paint.HeliostatProperties`."""
    a = properties.actuators

    def pair(key):
        return np.asarray([float(a[0][key]), float(a[1][key])], np.float64)

    actuators = {
        "increment": pair("increment"),
        "initial_stroke_length": pair("initial_stroke_length"),
        "offset": pair("offset"),
        "pivot_radius": pair("pivot_radius"),
        "initial_angle": pair("initial_angle"),
        "sign": np.where(pair("clockwise_axis_movement") == 0, 1.0, -1.0),
        "min_counts": pair("min_increment"),
        "max_counts": pair("max_increment"),
    }
    vec = lambda v: np.asarray(v, np.float64)  # noqa: E731
    return _build_geometry(
        vec(properties.position_lla),
        vec(origin_lla),
        actuators,
        vec(properties.joint_translation_1),
        vec(properties.joint_translation_2),
        vec(properties.concentrator_translation),
        np.asarray([a[i]["type_axis"] == "ideal" for i in range(2)]),
    )


@eqx.filter_jit
def _build_geometry(position_lla, origin_lla, actuators, v01, v12, v2m, ideal_axes) -> HeliostatGeometry:
    """:func:`geometry_from_properties`' arithmetic, compiled once."""
    pos = wgs84_to_enu(position_lla, origin_lla)
    return HeliostatGeometry.build(pos, LinearActuators(**actuators), v01, v12, v2m, ideal_axes=ideal_axes)


@eqx.filter_jit
def _record_poses(model, geometry, counts, sun_az_el_deg, spots_lla, origin_lla):
    """Per record: the pose of its counts turned onto its focal spot, and the sun."""

    def one(c, ae, spot):
        sun = sun_direction(jnp.deg2rad(ae[0]), jnp.deg2rad(ae[1]))
        return point_at(forward(model, geometry, c), sun, wgs84_to_enu(spot, origin_lla)), sun

    return jax.vmap(one)(counts, sun_az_el_deg, spots_lla)


def layout_from_properties(properties) -> FacetLayout:
    """:class:`FacetLayout` of a :class:`heliojax.paint.HeliostatProperties`."""
    if not properties.facets:
        raise DataError(properties.source, "facet_properties.facets", "no facets")
    return FacetLayout.from_arrays(
        np.asarray([f.translation_vector for f in properties.facets], np.float64),
        np.asarray([f.canting_e for f in properties.facets], np.float64),
        np.asarray([f.canting_n for f in properties.facets], np.float64),
    )


def target_from_tower(tower, name: str) -> TargetPlane:
    """The target ``name`` of a :class:`heliojax.paint.TowerFile` as a plane (ENU m):
    a planar calibration target from its corners, or the receiver (PAINT's
    ``convex_cylinder``) as the plane of its outer aperture corners
    (``receiver_outer_*``), on which its flux is then imaged."""
    entry = tower.targets.get(name)
    corners = ("upper_left", "upper_right", "lower_left", "lower_right")
    if entry is not None and entry.is_planar_target:
        names = corners
    elif entry is not None and all(f"receiver_outer_{c}" in entry.points for c in corners):
        names = tuple(f"receiver_outer_{c}" for c in corners)
    else:
        usable = sorted(
            k
            for k, e in tower.targets.items()
            if e.is_planar_target or all(f"receiver_outer_{c}" in e.points for c in corners)
        )
        raise DataError(tower.source, name, f"no such target with corners; the tower file has {', '.join(usable)}")
    lla = np.asarray([entry.points[c] for c in names], np.float64)
    points = np.asarray(_enu_of_corners(lla, np.asarray(tower.origin_lla, np.float64)))
    check_target_corners(tower.source, f"{name}.coordinates", *points, normal=entry.normal)
    distance = float(np.hypot(*points.mean(axis=0)[:2]))
    if not distance <= MAX_HELIOSTAT_DISTANCE_M:
        raise DataError(
            tower.source,
            f"{name}.coordinates",
            f"{distance / 1000:.4g} km from the plant's reference point (more than "
            f"{MAX_HELIOSTAT_DISTANCE_M / 1000:g} km: not a target of this plant)",
        )
    return _plane_from_corners(jnp.asarray(points))


@jax.jit
def _enu_of_corners(corners_lla, origin_lla):
    """:func:`target_from_tower`'s geodesy (corners UL, UR, LL, LR in WGS84 to ENU m), compiled once."""
    return jax.vmap(lambda p: wgs84_to_enu(p, origin_lla))(corners_lla)


@jax.jit
def _plane_from_corners(points) -> TargetPlane:
    """:func:`target_from_tower`'s plane of ENU corners UL, UR, LL, LR, compiled once."""
    return TargetPlane.from_corners(points[0], points[1], points[2], points[3])


@dataclasses.dataclass(frozen=True)
class FluxComparison:
    """Traced vs measured flux of one calibration record (metres on the target plane).

    Attributes:
        heliostat_id, record_id, target_name: what was compared.
        centroid_distance_m: traced vs measured (``-flux.png``) centroid distance.
        ncc: normalised cross-correlation of the full-target images.
        ncc_centred: normalised cross-correlation of the 6 x 6 m centred images.
        png_vs_record_m: measured PNG centroid vs the record's focal spot (checks the
            assumed PNG extent/orientation; UTIS, else HeliOS).
        traced_vs_record_m: traced centroid vs the record's focal spot.
        kl_centred: :func:`kl_divergence` of the measured from the traced centred image.
        widths_traced_m, widths_measured_m: ``(2,)`` :func:`spot_widths` ``(sigma_u,
            sigma_v)`` of the centred images.
        pointing_corrected: whether the pose was turned onto the record's focal spot.
        traced, measured: ``(256, 256)`` images on ``grid`` (traced in W/m^2,
            measured background-free relative brightness).
        traced_centred, measured_centred: the centred images on ``grid_centred``.
    """

    heliostat_id: str
    record_id: int
    target_name: str
    centroid_distance_m: float
    ncc: float
    ncc_centred: float
    png_vs_record_m: float
    traced_vs_record_m: float
    kl_centred: float
    widths_traced_m: np.ndarray
    widths_measured_m: np.ndarray
    pointing_corrected: bool
    traced: np.ndarray
    measured: np.ndarray
    traced_centred: np.ndarray
    measured_centred: np.ndarray
    grid: ImageGrid
    grid_centred: ImageGrid

    def summary(self) -> dict:
        """The scalar fields as a JSON-able dict."""
        out = {
            k: getattr(self, k)
            for k in (
                "heliostat_id",
                "record_id",
                "target_name",
                "centroid_distance_m",
                "ncc",
                "ncc_centred",
                "kl_centred",
                "png_vs_record_m",
                "traced_vs_record_m",
                "pointing_corrected",
            )
        }
        out["widths_traced_m"] = [float(x) for x in self.widths_traced_m]
        out["widths_measured_m"] = [float(x) for x in self.widths_measured_m]
        return out


def default_sunshape() -> AbstractSunShape:
    """Sun shape used for the PAINT comparisons: Buie (csr 0.05) with 1.5 mrad
    Gaussian slope error (an assumed typical value: no deflectometry is shipped)."""
    return EffectiveSun(BuieSun(0.05), 1.5e-3)


def compare_record(
    record_path: str | os.PathLike,
    properties_path: str | os.PathLike,
    tower_path: str | os.PathLike,
    *,
    model: AbstractKinematicModel | None = None,
    surface: SurfacePoints | None = None,
    sunshape: AbstractSunShape | None = None,
    key=None,
    rays_per_point: int = 64,
    steps: int = 4,
    resolution: tuple[int, int] = (32, 32),
    correct_pointing: bool = False,
) -> FluxComparison:
    """Align a heliostat with a record's motor counts, trace its flux and compare it
    with the record's ``-flux.png`` / ``-flux-centered.png`` (same folder, same ID).

    Args:
        record_path: ``<H>/Calibration/<ID>-calibration-properties.json``.
        properties_path: the heliostat's properties JSON.
        tower_path: the tower-measurements JSON.
        model: kinematic model (default: nominal :class:`ActuatorModel`, i.e. PAINT's
            geometry); pass calibrated parameters here.
        surface: mirror in the surface frame (default: ideal canted facets from the
            properties, ``resolution`` points per facet).
        sunshape: default :func:`default_sunshape`.
        key: PRNG key (default ``jax.random.key(0)``).
        rays_per_point, steps: rays per surface point = their product.
        resolution: points per facet of the default ideal surface.
        correct_pointing: turn the kinematic pose onto the record's measured focal
            spot (:func:`point_at`; UTIS, else HeliOS), so that the spot's shape, not
            the pointing error, is compared.
    """
    record_path = Path(record_path)
    tower = read_tower(tower_path)
    props = read_heliostat_properties(properties_path)
    record = read_calibration_record(record_path, heliostat_id=props.heliostat_id)
    model = ActuatorModel.nominal(jnp.float64) if model is None else model
    sunshape = default_sunshape() if sunshape is None else sunshape
    key = jax.random.key(0) if key is None else key
    target = target_from_tower(tower, record.target_name)
    geometry = geometry_from_properties(props, tower.origin_lla)
    if surface is None:
        surface = ideal_surface(layout_from_properties(props), resolution)
    sun = sun_direction(jnp.deg2rad(record.sun_azimuth_deg), jnp.deg2rad(record.sun_elevation_deg))
    counts = jnp.asarray([record.axis_1_counts, record.axis_2_counts], jnp.float64)
    pose = forward(model, geometry, counts)
    spot = record.focal_spot_utis or record.focal_spot_helios
    origin = jnp.asarray(tower.origin_lla, jnp.float64)
    spot_enu = None if spot is None else wgs84_to_enu(jnp.asarray(spot, jnp.float64), origin)
    if correct_pointing:
        if spot_enu is None:
            raise DataError(record_path, "focal_spot", "no focal spot to correct the pointing with")
        pose = point_at(pose, sun, spot_enu)

    measured, measured_c = measured_images(record_path)

    grid = ImageGrid.for_target(target, measured.shape)

    def trace(k, g):  # flux_image is compiled; the surface is an argument, so every record reuses one program
        return flux_image(k, surface, pose, sun, target, g, sunshape, rays_per_point=rays_per_point, steps=steps)

    # centroid from a grid with a 10 m margin, so a spot partly off the target is not biased
    wide = ImageGrid(grid.u_min - 10.0, grid.u_max + 10.0, grid.v_min - 10.0, grid.v_max + 10.0, shape=(256, 256))
    c_measured = image_centroid(measured, grid)
    with progress_bar(None, logger=log, desc="tracing the comparison", total=3, unit="image") as bar:
        traced = np.asarray(trace(key, grid), np.float64)
        bar.update()
        c_traced = image_centroid(np.asarray(trace(jax.random.fold_in(key, 2), wide), np.float64), wide)
        bar.update()
        # no ray on the wide grid (a NaN centroid): the window at the target's centre, also dark
        u0, v0 = c_traced if np.isfinite(c_traced).all() else (0.0, 0.0)
        grid_c = ImageGrid.centred(u0, v0, *CENTRED_WINDOW_M, shape=measured_c.shape)
        traced_c = np.asarray(trace(jax.random.fold_in(key, 1), grid_c), np.float64)
        bar.update()

    if spot_enu is not None:
        spot_uv = np.asarray(target.to_plane(spot_enu))
        png_vs_record = float(np.linalg.norm(c_measured - spot_uv))
        traced_vs_record = float(np.linalg.norm(c_traced - spot_uv))
    else:
        png_vs_record = traced_vs_record = float("nan")
    return FluxComparison(
        heliostat_id=props.heliostat_id,
        record_id=record.record_id,
        target_name=record.target_name,
        centroid_distance_m=float(np.linalg.norm(c_traced - c_measured)),
        ncc=normalised_cross_correlation(traced, measured),
        ncc_centred=normalised_cross_correlation(traced_c, measured_c),
        png_vs_record_m=png_vs_record,
        traced_vs_record_m=traced_vs_record,
        kl_centred=kl_divergence(measured_c, traced_c),
        widths_traced_m=spot_widths(traced_c, grid_c),
        widths_measured_m=spot_widths(measured_c, _centred_grid(measured_c.shape)),
        pointing_corrected=correct_pointing,
        traced=traced,
        measured=measured,
        traced_centred=traced_c,
        measured_centred=measured_c,
        grid=grid,
        grid_centred=grid_c,
    )


@typing.final
class FluxRecords(eqx.Module):
    """Measured flux images of one heliostat with what they were taken with, ready
    for tracing (batched over ``n`` records; ENU m).

    Attributes:
        heliostat_id: the heliostat.
        record_ids: ``(n,)`` calibration record ids.
        images: ``(n, k, k)`` measured ``-flux-centered`` images, background removed,
            block-averaged to ``k`` pixels, relative brightness.
        poses: :class:`Pose` ``(n, ...)``: the record's motor counts through
            ``model``, turned onto its measured focal spot (:func:`point_at`).
        suns: ``(n, 3)`` unit vectors to the sun.
        targets: :class:`TargetPlane` ``(n, ...)`` of each record.
        grids: :class:`ImageGrid` ``(n,)``: 6 x 6 m windows about the measured centroids.
        geometry: the heliostat's :class:`HeliostatGeometry` (from its properties).
        layout: its :class:`FacetLayout`.
        skipped: ``(record, reason)`` of each record left out by ``flux_records(...,
            skip_bad=True)`` (``record`` its id, or its file name when the id is unreadable).
    """

    heliostat_id: str = eqx.field(static=True)
    record_ids: tuple[int, ...] = eqx.field(static=True)
    images: Float[Array, "n k k"]
    poses: Pose
    suns: Float[Array, "n 3"]
    targets: TargetPlane
    grids: ImageGrid
    geometry: HeliostatGeometry
    layout: FacetLayout
    skipped: tuple[tuple[str, str], ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        n = len(self.record_ids)
        if self.images.shape[0] != n or self.suns.shape[0] != n or self.poses.normal.shape[0] != n:
            raise ValueError(f"{n} record ids but {self.images.shape[0]} images, {self.suns.shape[0]} suns")

    def subset(self, index) -> FluxRecords:
        """The records at ``index`` (a list of positions)."""
        idx = np.asarray(index, int)
        take = lambda t: jax.tree_util.tree_map(lambda x: x[idx], t)  # noqa: E731
        return FluxRecords(
            heliostat_id=self.heliostat_id,
            record_ids=tuple(self.record_ids[i] for i in idx),
            images=self.images[idx],
            poses=take(self.poses),
            suns=self.suns[idx],
            targets=take(self.targets),
            grids=take(self.grids),
            geometry=self.geometry,
            layout=self.layout,
            skipped=self.skipped,
        )


def flux_records(
    records: list[tuple[Path, Path]],
    tower_path: str | os.PathLike,
    *,
    model: AbstractKinematicModel | None = None,
    pixels: int = 64,
    skip_bad: bool = False,
) -> FluxRecords:
    """Load one heliostat's flux records (``(record JSON, properties JSON)`` pairs as
    :func:`flux_sample_records` lists them) for reconstruction or validation.

    Args:
        skip_bad: leave out, with a warning naming the file and the reason, a record
            that cannot be used (a damaged or blank flux PNG, a malformed record JSON,
            no focal spot, an unknown target) instead of raising; the records left out
            are :attr:`FluxRecords.skipped`. The properties and tower files are needed
            by every record: an error in them is raised all the same.

    Raises:
        DataError: a record of another heliostat, one without a focal spot, or a
            ``-flux-centered.png`` whose size is not a multiple of ``pixels`` (without
            ``skip_bad``); with ``skip_bad``, when no record is left.
        ValueError: ``records`` is empty.
    """
    if not records:
        raise ValueError("no flux records given")
    tower = read_tower(tower_path)
    model = ActuatorModel.nominal(jnp.float64) if model is None else model
    props = read_heliostat_properties(records[0][1])
    geometry = geometry_from_properties(props, tower.origin_lla)
    ids, images, counts, az_el, spots, targets, grids = [], [], [], [], [], [], []
    skipped: list[tuple[str, str]] = []
    for rec_path, _ in records:
        rec_path = Path(rec_path)
        try:
            loaded = _flux_record(rec_path, props.heliostat_id, tower, pixels)
        except DataError as e:
            if not skip_bad:
                raise
            name = rec_path.name.replace("-calibration-properties.json", "")
            skipped.append((name, str(e)))
            log.warning(f"record {name} of {props.heliostat_id} left out: {e}")
            continue
        for out, value in zip((ids, images, counts, az_el, spots, targets, grids), loaded, strict=True):
            out.append(value)
    if not ids:
        raise DataError(
            Path(records[0][0]).parent,
            None,
            f"no usable flux record of {props.heliostat_id}: all {len(records)} were left out "
            f"({'; '.join(f'{r}: {why}' for r, why in skipped[:3])})",
        )
    stack = lambda xs: jax.tree_util.tree_map(lambda *x: jnp.stack(x), *xs)  # noqa: E731
    f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
    poses, suns = _record_poses(model, geometry, f64(counts), f64(az_el), f64(spots), f64(tower.origin_lla))
    return FluxRecords(
        heliostat_id=props.heliostat_id,
        record_ids=tuple(ids),
        images=jnp.asarray(np.stack(images)),
        poses=poses,
        suns=suns,
        targets=stack(targets),
        grids=stack(grids),
        geometry=geometry,
        layout=layout_from_properties(props),
        skipped=tuple(skipped),
    )


def _flux_record(rec_path: Path, heliostat: str, tower, pixels: int) -> tuple:
    """One record of :func:`flux_records`: ``(id, image, counts, (azimuth, elevation),
    focal spot, target, grid)``; a :class:`DataError` if it cannot be used."""
    record = read_calibration_record(rec_path, heliostat_id=heliostat)
    spot = record.focal_spot_utis or record.focal_spot_helios
    if spot is None:
        raise DataError(rec_path, "focal_spot", "no focal spot")
    target = target_from_tower(tower, record.target_name)
    full, centred = measured_images(rec_path)
    centre = image_centroid(full, ImageGrid.for_target(target, full.shape))
    k = centred.shape[0] // pixels
    if centred.shape != (k * pixels, k * pixels):
        raise DataError(
            rec_path.parent / rec_path.name.replace("-calibration-properties.json", "-flux-centered.png"),
            None,
            f"{centred.shape} pixels, not a multiple of {pixels}",
        )
    return (
        record.record_id,
        centred.reshape(pixels, k, pixels, k).mean(axis=(1, 3)),
        [record.axis_1_counts, record.axis_2_counts],
        [record.sun_azimuth_deg, record.sun_elevation_deg],
        spot,
        target,
        ImageGrid.centred(centre[0], centre[1], *CENTRED_WINDOW_M, shape=(pixels, pixels)),
    )


def _centred_grid(shape) -> ImageGrid:
    """Grid of a measured ``-flux-centered`` image: 6 x 6 m about its own centroid."""
    w, h = CENTRED_WINDOW_M
    return ImageGrid.centred(0.0, 0.0, w, h, shape=shape)


def flux_sample_records(root: str | os.PathLike) -> list[tuple[Path, Path]]:
    """``(record JSON, properties JSON)`` of every record with a flux PNG under
    ``root`` (PAINT layout ``<H>/Calibration``, ``<H>/Properties``)."""
    out = []
    for png in sorted(Path(root).glob("*/Calibration/*-flux.png")):
        h = png.parent.parent.name
        rec = png.parent / png.name.replace("-flux.png", "-calibration-properties.json")
        props = png.parent.parent / "Properties" / f"{h}-heliostat-properties.json"
        if rec.exists() and props.exists():
            out.append((rec, props))
    return out


def comparison_figure(comparison: FluxComparison, ax=None):
    """Traced and measured images side by side (full target and centred window)."""
    plt = pyplot()
    if ax is None:
        fig, ax = plt.subplots(1, 4, figsize=(16, 4.2), layout="constrained")
    else:
        fig = np.ravel(ax)[0].figure
    ax = np.ravel(ax)
    g, gc = comparison.grid, comparison.grid_centred
    ext = [float(g.u_min), float(g.u_max), float(g.v_min), float(g.v_max)]
    extc = [float(gc.u_min), float(gc.u_max), float(gc.v_min), float(gc.v_max)]
    panels = (
        (comparison.traced, ext, "traced, whole target", "flux density [W/m$^2$]"),
        (comparison.measured, ext, "measured (flux.png)", "relative brightness"),
        (comparison.traced_centred, extc, "traced, window on its centroid", "flux density [W/m$^2$]"),
        (comparison.measured_centred, [-3, 3, -3, 3], "measured (flux-centered.png)", "relative brightness"),
    )
    for a, (img, e, title, unit) in zip(ax, panels, strict=True):
        im = a.imshow(img, extent=e, origin="upper", cmap="inferno")
        fig.colorbar(im, ax=a, label=unit, shrink=0.85)
        a.set_title(title, fontsize=9)
        a.set_xlabel("u, along the target [m]")
        a.set_ylabel("v, up the target [m]")
    fig.suptitle(
        f"{comparison.heliostat_id} record {comparison.record_id}: centroid distance "
        f"{comparison.centroid_distance_m:.2f} m, NCC {comparison.ncc:.2f} / centred {comparison.ncc_centred:.2f}",
        fontsize=10,
    )
    return fig


__all__ = [
    "CENTRED_WINDOW_M",
    "MAX_UNIFORM_SPREAD",
    "FluxComparison",
    "FluxRecords",
    "compare_record",
    "comparison_figure",
    "default_sunshape",
    "flux_records",
    "flux_sample_records",
    "geometry_from_properties",
    "image_centroid",
    "kl_divergence",
    "point_at",
    "spot_widths",
    "layout_from_properties",
    "load_flux_png",
    "measured_images",
    "normalised_cross_correlation",
    "remove_background",
    "target_from_tower",
    "uniform_spread",
]
