"""Surface reconstruction from flux images by gradient descent through the tracer.

Unknowns: height offsets ``dz`` of the NURBS control points (``(f, n_u, n_v)``,
metres, added to ``control_points[..., 2]`` of an initial — usually ideal —
:class:`NurbsFacets`). For ``n`` flux images ``M_k`` taken with poses ``pose_k``
and sun directions ``s_k``, the loss is

    L(dz) = mean_k |F_k(dz) - M_k|^2 / |M_k|^2                       (data)
          + flux_weight * mean_k (sum F_k / sum M_k - 1)^2          (flux conservation)
          + smoothness * sum |D2 dz|^2 / (n_u n_v)                  (curvature of the patch)
          + 1e-6 * mean dz^2 / (1 mm)^2                            (fixes the per-facet piston)

with ``F_k`` the traced flux image (W/m^2 on the same grid). With
``relative=True`` (camera images of relative brightness, such as PAINT's flux
PNGs) both images are normalised to unit sum before the data term and the
flux-conservation term is dropped. Each optimisation
step traces with a fresh key (``fold_in(key, step)``), so the optimiser averages
the Monte Carlo noise out instead of fitting one fixed noise realisation.
Optimiser: ``optax.adam``; the whole step is jitted once.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._geometry import TargetPlane
from .._heliostat import Pose
from .._progress import progress_bar
from ._flux import ImageGrid, aim_pose, flux_images
from ._nurbs import NurbsFacets
from ._sunshape import AbstractSunShape, PillboxSun
from ._surfaces import FacetLayout

log = logging.getLogger(__name__)


def with_height_offsets(facets: NurbsFacets, dz: Float[Array, "f nu nv"]) -> NurbsFacets:
    """``facets`` with ``dz`` (m) added to the control points' heights."""
    return eqx.tree_at(lambda f: f.control_points, facets, facets.control_points.at[..., 2].add(dz))


def _second_differences(dz):
    a = dz[..., 2:, :] - 2 * dz[..., 1:-1, :] + dz[..., :-2, :]
    b = dz[..., :, 2:] - 2 * dz[..., :, 1:-1] + dz[..., :, :-2]
    return jnp.sum(a**2) + jnp.sum(b**2)


@dataclasses.dataclass(frozen=True)
class ReconstructionResult:
    """Output of :func:`reconstruct_surface`.

    Attributes:
        facets: the reconstructed :class:`NurbsFacets`.
        dz: ``(f, n_u, n_v)`` control-point height offsets, m.
        losses: loss per step.
    """

    facets: NurbsFacets
    dz: np.ndarray
    losses: np.ndarray


def loss_window(steps: int) -> int:
    """Steps averaged at each end of a loss curve of ``steps`` steps to compare its start
    with its end: a fifth of the steps, at least 1 and at most 10 (the loss of one step
    is a draw of rays, so a few are averaged; a window wider than a fifth of the run
    would blur the start into the end, and one of 10 steps already averages the noise).
    Used both for the ``loss_first_last`` of a reconstruction's summary and for the
    CLI's divergence warning, so the two always agree."""
    return max(1, min(10, int(steps) // 5))


def flux_loss(
    dz,
    key: PRNGKeyArray,
    initial: NurbsFacets,
    images: Float[Array, "n ny nx"],
    poses: Pose,
    suns: Float[Array, "n 3"],
    target: TargetPlane,
    grid: ImageGrid,
    sunshape: AbstractSunShape,
    *,
    resolution: tuple[int, int],
    rays_per_point: int,
    smoothness: float,
    flux_weight: float,
    dni: float,
    relative: bool = False,
) -> Float[Array, ""]:
    """The reconstruction loss (see the module docstring) at height offsets ``dz``."""
    n = images.shape[0]
    surf = with_height_offsets(initial, dz).evaluate(resolution)
    surfs = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), surf)
    pred = flux_images(key, surfs, poses, suns, target, grid, sunshape, rays_per_point=rays_per_point, dni=dni)
    pred = pred.astype(images.dtype)
    if relative:
        unit = lambda x: x / jnp.maximum(jnp.sum(x, axis=(-2, -1), keepdims=True), 1e-30)  # noqa: E731
        pred, images = unit(pred), unit(images)
        flux_weight = 0.0
    norm = jnp.sum(images**2, axis=(-2, -1))
    data = jnp.mean(jnp.sum((pred - images) ** 2, axis=(-2, -1)) / norm)
    ratio = jnp.sum(pred, axis=(-2, -1)) / jnp.sum(images, axis=(-2, -1))
    conservation = jnp.mean((ratio - 1.0) ** 2)
    nu, nv = dz.shape[-2:]
    smooth = _second_differences(dz) / (nu * nv)
    piston = jnp.mean(dz**2) / 1e-6
    regular = (smoothness * smooth / 1e-6 + 1e-6 * piston).astype(data.dtype)
    return data + flux_weight * conservation.astype(data.dtype) + regular


def reconstruct_surface(
    key: PRNGKeyArray,
    initial: NurbsFacets,
    images: Float[ArrayLike, "n ny nx"],
    poses: Pose,
    suns: Float[ArrayLike, "n 3"],
    target: TargetPlane,
    grid: ImageGrid,
    sunshape: AbstractSunShape,
    *,
    steps: int = 300,
    learning_rate: float = 2e-4,
    resolution: tuple[int, int] = (16, 16),
    rays_per_point: int = 32,
    smoothness: float = 1e-3,
    flux_weight: float = 1.0,
    dni: float = 1000.0,
    relative: bool = False,
    callback: Callable[[int, float], None] | None = None,
) -> ReconstructionResult:
    """Recover control-point heights of one heliostat from ``n`` flux images.

    Args:
        key: PRNG key; step ``j`` traces with ``fold_in(key, j)``.
        initial: starting facets (e.g. :meth:`NurbsFacets.ideal`), unbatched ``(f, ...)``.
        images: ``(n, ny, nx)`` measured flux (W/m^2 for ``dni`` W/m^2 of sun).
        poses: ``(n,)`` batched poses of the records (e.g. from ``forward``).
        suns: ``(n, 3)`` sun directions.
        target: the target plane (shared or batched ``(n,)``).
        grid: the images' grid (shared or batched).
        sunshape: sun shape used for the predictions.
        steps: optimiser steps.
        learning_rate: Adam step size (m of control height).
        resolution: evaluation points per facet for tracing.
        rays_per_point: rays per point per image and step.
        smoothness: weight of the second differences of ``dz`` (per (1 mm)^2).
        flux_weight: weight of the total-power (flux conservation) term.
        dni: W/m^2.
        relative: images of relative brightness: compare unit-sum images, no
            flux-conservation term.
        callback: ``callback(step, loss)`` after every step (host side).
    """
    images = jnp.asarray(images, jnp.float32)
    suns = jnp.asarray(suns)
    dz = jnp.zeros(initial.control_points.shape[:-1], initial.control_points.dtype)
    opt = optax.adam(learning_rate)
    state = opt.init(dz)
    kw = dict(
        resolution=resolution,
        rays_per_point=rays_per_point,
        smoothness=smoothness,
        flux_weight=flux_weight,
        dni=dni,
        relative=relative,
    )

    @jax.jit
    def step(dz, state, j):
        loss, g = jax.value_and_grad(flux_loss)(
            dz, jax.random.fold_in(key, j), initial, images, poses, suns, target, grid, sunshape, **kw
        )
        with jax.numpy_dtype_promotion("standard"):  # optax mixes Python floats with its int32 step count
            updates, state = opt.update(g, state, dz)
        return optax.apply_updates(dz, updates), state, loss

    losses = []
    for j in progress_bar(range(steps), logger=log, desc="surface reconstruction", unit="step"):
        dz, state, loss = step(dz, state, j)
        losses.append(float(loss))
        if callback is not None:
            callback(j, losses[-1])
    return ReconstructionResult(facets=with_height_offsets(initial, dz), dz=np.asarray(dz), losses=np.asarray(losses))


def normal_rms_error_mrad(a: NurbsFacets, b: NurbsFacets, resolution: tuple[int, int] = (24, 24)) -> float:
    """Area-weighted RMS angle (mrad) between the normals of two patches with the same
    parameterisation, on a cell-centred parameter grid."""
    sa, sb = a.evaluate(resolution), b.evaluate(resolution)
    cross = jnp.linalg.norm(jnp.cross(sa.normals, sb.normals), axis=-1)
    ang = jnp.arctan2(cross, jnp.sum(sa.normals * sb.normals, axis=-1))
    w = sa.areas
    return float(jnp.sqrt(jnp.sum(w * ang**2) / jnp.sum(w)) * 1e3)


@dataclasses.dataclass(frozen=True)
class SyntheticScene:
    """A reconstruction benchmark: a heliostat whose hidden surface carries bumps.

    Attributes:
        ideal: the flat-canted starting facets.
        truth: the hidden deformed facets.
        images: ``(n, ny, nx)`` flux images of ``truth`` (W/m^2).
        poses, suns, target, grid: what the images were taken with.
        sunshape: the sun shape used.
    """

    ideal: NurbsFacets
    truth: NurbsFacets
    images: Array
    poses: Pose
    suns: Array
    target: TargetPlane
    grid: ImageGrid
    sunshape: AbstractSunShape


def synthetic_scene(
    seed: int = 1,
    n_images: int = 6,
    bump_m: tuple[float, float] = (0.6e-3, 1.2e-3),
    n_ctrl: int = 5,
    pixels: int = 64,
    rays_per_point: int = 1024,
) -> SyntheticScene:
    """Four 1.6 x 1.28 m facets (weak canting, focus 200 m) 40 m north of a 5 x 5 m
    vertical target; each facet's control heights carry a Gaussian bump of random
    sign and amplitude in ``bump_m`` (max slopes ~1-3 mrad); ``n_images`` flux
    images (pillbox sun) for suns from the east through south to the west."""
    f = 200.0
    cent = np.array([[-0.81, 0.645], [0.81, 0.645], [-0.81, -0.645], [0.81, -0.645]])
    ce = np.array([[0.8, 0, c[0] / (2 * f) * 0.8] for c in cent])
    cn = np.array([[0, 0.64, c[1] / (2 * f) * 0.64] for c in cent])
    ideal = NurbsFacets.ideal(FacetLayout.from_arrays(np.c_[cent, np.zeros(4)], ce, cn), n_ctrl=(n_ctrl, n_ctrl))
    rng = np.random.default_rng(seed)
    g = np.linspace(-1, 1, n_ctrl)
    X, Y = np.meshgrid(g, g, indexing="ij")
    dz = np.zeros((4, n_ctrl, n_ctrl))
    for k in range(4):
        bx, by = rng.uniform(-0.5, 0.5, 2)
        dz[k] = rng.uniform(*bump_m) * rng.choice([-1, 1]) * np.exp(-((X - bx) ** 2 + (Y - by) ** 2) / 0.5)
    truth = with_height_offsets(ideal, jnp.asarray(dz))
    target = TargetPlane.from_corners(
        jnp.asarray([2.5, 0, 22.5]),
        jnp.asarray([-2.5, 0, 22.5]),
        jnp.asarray([2.5, 0, 17.5]),
        jnp.asarray([-2.5, 0, 17.5]),
    )
    grid = ImageGrid.for_target(target, (pixels, pixels))
    centre = jnp.asarray([0.0, 40.0, 2.0])
    suns, poses = [], []
    for az, el in zip(np.linspace(-60, 60, n_images), 30 + 25 * np.cos(np.linspace(-1.2, 1.2, n_images))):
        a, e = np.deg2rad(az), np.deg2rad(el)
        s = jnp.asarray([np.cos(e) * np.sin(a), -np.cos(e) * np.cos(a), np.sin(e)])
        suns.append(s)
        poses.append(aim_pose(centre, s, target.centre))
    suns = jnp.stack(suns)
    poses = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *poses)
    sunshape = PillboxSun()
    surf = truth.evaluate((16, 16))
    surfs = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n_images,) + x.shape), surf)
    images = flux_images(
        jax.random.key(seed + 1000),
        surfs,
        poses,
        suns,
        target,
        grid,
        sunshape,
        rays_per_point=rays_per_point // 4,
        steps=4,
    )
    return SyntheticScene(ideal, truth, images, poses, suns, target, grid, sunshape)


__all__ = [
    "ReconstructionResult",
    "SyntheticScene",
    "synthetic_scene",
    "flux_loss",
    "loss_window",
    "normal_rms_error_mrad",
    "reconstruct_surface",
    "with_height_offsets",
]
