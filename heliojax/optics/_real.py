"""Surface reconstruction from a heliostat's real flux records (PAINT camera images).

:func:`reconstruct_from_records` runs :func:`reconstruct_surface` on some of a
heliostat's :class:`FluxRecords` (relative brightness; poses from the records'
motor counts turned onto their focal spots) and traces every record with the
ideal, the reconstructed and any reference surfaces (e.g. deflectometry from an
ARTIST scenario), so that training and held-out records can be judged alike.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

from .._plotting import pyplot
from ._compare import FluxRecords, kl_divergence, normalised_cross_correlation
from ._flux import flux_images
from ._nurbs import NurbsFacets
from ._reconstruct import ReconstructionResult, loss_window, reconstruct_surface
from ._sunshape import AbstractSunShape, BuieSun


@dataclasses.dataclass(frozen=True)
class RecordsReconstruction:
    """Result of :func:`reconstruct_from_records`.

    Attributes:
        heliostat_id: the heliostat.
        record_ids: ``(n,)`` every record, in the order of the images.
        train: positions of the records used for the reconstruction.
        ideal: the starting (ideal canted) facets.
        result: the :class:`ReconstructionResult` (facets, height offsets, losses).
        traced: surface name (``"ideal"``, ``"reconstructed"`` and the references) ->
            ``(n, k, k)`` traced images of every record on its window (W/m^2).
        ncc, kl: surface name -> ``(n,)`` NCC and KL divergence against the measured images.
    """

    heliostat_id: str
    record_ids: tuple[int, ...]
    train: tuple[int, ...]
    ideal: NurbsFacets
    result: ReconstructionResult
    traced: Mapping[str, np.ndarray]
    ncc: Mapping[str, np.ndarray]
    kl: Mapping[str, np.ndarray]

    @property
    def held_out(self) -> tuple[int, ...]:
        """Positions of the records not used for the reconstruction."""
        return tuple(i for i in range(len(self.record_ids)) if i not in self.train)

    def summary(self) -> dict:
        """JSON-able scores per record and surface, and ``loss_first_last``: the mean
        loss over the first and over the last ``loss_window_steps`` steps
        (:func:`heliojax.optics.loss_window`: a fifth of the steps, 1 to 10; with one
        step the two are the same)."""
        rows = []
        for i, rid in enumerate(self.record_ids):
            row: dict = {"record": rid, "role": "train" if i in self.train else "held out"}
            for name in self.ncc:
                row[f"ncc_{name}"] = float(self.ncc[name][i])
                row[f"kl_{name}"] = float(self.kl[name][i])
            rows.append(row)
        losses = np.asarray(self.result.losses, np.float64)
        k = loss_window(losses.size)
        return {
            "heliostat": self.heliostat_id,
            "records": rows,
            "loss_first_last": [float(losses[:k].mean()), float(losses[-k:].mean())],
            "loss_window_steps": k,
        }


@eqx.filter_jit
def _trace_all(facets: NurbsFacets, records: FluxRecords, key, sunshape, rays_per_point: int, resolution):
    n = records.images.shape[0]
    surface = facets.evaluate(resolution)
    surfaces = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), surface)
    return flux_images(
        key,
        surfaces,
        records.poses,
        records.suns,
        records.targets,
        records.grids,
        sunshape,
        rays_per_point=rays_per_point,
        steps=4,
    )


def reconstruct_from_records(
    records: FluxRecords,
    train: Sequence[int] | None = None,
    *,
    key: PRNGKeyArray | None = None,
    references: Mapping[str, NurbsFacets] | None = None,
    sunshape: AbstractSunShape | None = None,
    n_ctrl: int = 8,
    steps: int = 300,
    learning_rate: float = 5e-5,
    smoothness: float = 1e-2,
    resolution: tuple[int, int] = (16, 16),
    rays_per_point: int = 32,
    evaluation_rays: int = 64,
) -> RecordsReconstruction:
    """Reconstruct a heliostat's NURBS heights from the records at ``train``
    (positions; default all) and score every record.

    Args:
        records: the heliostat's flux records (:func:`heliojax.optics.flux_records`).
        train: positions of the training records (default all).
        key: PRNG key (default ``jax.random.key(0)``).
        references: further surfaces to trace and score, e.g. ``{"deflectometry": ...}``.
        sunshape: default Buie, circumsolar ratio 0.05.
        n_ctrl: control points per facet and direction of the reconstructed patches.
        steps, learning_rate, smoothness, resolution, rays_per_point: of
            :func:`heliojax.optics.reconstruct_surface` (``relative=True``).
        evaluation_rays: rays per point (x 4 steps) for the scoring traces.
    """
    n = len(records.record_ids)
    train = tuple(range(n)) if train is None else tuple(int(i) for i in train)
    if not train or any(not 0 <= i < n for i in train):
        raise ValueError(f"train positions {train} must be a non-empty subset of 0..{n - 1}")
    key = jax.random.key(0) if key is None else key
    sunshape = BuieSun(0.05) if sunshape is None else sunshape
    ideal = NurbsFacets.ideal(records.layout, n_ctrl=(n_ctrl, n_ctrl))
    fit = records.subset(list(train))
    result = reconstruct_surface(
        key,
        ideal,
        fit.images,
        fit.poses,
        fit.suns,
        fit.targets,
        fit.grids,
        sunshape,
        steps=steps,
        learning_rate=learning_rate,
        smoothness=smoothness,
        resolution=resolution,
        rays_per_point=rays_per_point,
        relative=True,
    )
    surfaces = {"ideal": ideal, "reconstructed": result.facets, **(references or {})}
    eval_key = jax.random.fold_in(key, 10**6)
    traced, ncc, kl = {}, {}, {}
    measured = np.asarray(records.images, np.float64)
    for name, facets in surfaces.items():
        img = np.asarray(_trace_all(facets, records, eval_key, sunshape, evaluation_rays, (24, 24)), np.float64)
        traced[name] = img
        ncc[name] = np.asarray([normalised_cross_correlation(a, b) for a, b in zip(img, measured, strict=True)])
        kl[name] = np.asarray([kl_divergence(b, a) for a, b in zip(img, measured, strict=True)])
    return RecordsReconstruction(
        heliostat_id=records.heliostat_id,
        record_ids=records.record_ids,
        train=train,
        ideal=ideal,
        result=result,
        traced=traced,
        ncc=ncc,
        kl=kl,
    )


def normal_deviation_map(
    facets: NurbsFacets, reference: NurbsFacets, resolution: tuple[int, int] = (24, 24)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angle between the normals of ``facets`` and of ``reference`` (one heliostat,
    the same facets), at the reference's sample points.

    ``facets`` must be height-field patches (``x, y`` linear in ``u, v``, as built by
    :meth:`NurbsFacets.ideal` or :func:`fit_nurbs`); ``reference`` may be any
    parameterisation (e.g. ARTIST's).

    Returns:
        ``(points (f, p, 3) in the surface frame (m), angles (f, p) in mrad, areas (f, p) in m^2)``.
    """
    s = reference.evaluate(resolution)
    f = reference.control_points.shape[-4]
    points = np.asarray(s.points).reshape(f, -1, 3)
    local = points - np.asarray(reference.translations)[:, None, :]
    normals = np.asarray(s.normals).reshape(f, -1, 3)
    n = np.asarray(facets.normals_at(jnp.asarray(local[..., :2], facets.control_points.dtype)))
    cross = np.linalg.norm(np.cross(n, normals), axis=-1)
    angles = np.arctan2(cross, np.sum(n * normals, axis=-1)) * 1e3
    return points, angles, np.asarray(s.areas).reshape(f, -1)


def normal_deviation_mrad(facets: NurbsFacets, reference: NurbsFacets, resolution: tuple[int, int] = (24, 24)) -> float:
    """Area-weighted RMS of :func:`normal_deviation_map` (mrad)."""
    _, angles, areas = normal_deviation_map(facets, reference, resolution)
    return float(np.sqrt(np.sum(areas * angles**2) / np.sum(areas)))


def low_order_shape(facets: NurbsFacets, resolution: tuple[int, int] = (24, 24)) -> list[dict]:
    """Per facet, the area-weighted least-squares paraboloid
    ``z = c0 + c1 x + c2 y + c3 (x^2 + y^2)`` of its facet-local points: the focal
    length ``1 / (4 c3)`` (m; negative for a convex facet, huge for a flat one) and
    the tilt ``(c1, c2)`` (mrad)."""
    s = facets.evaluate(resolution)
    f = facets.control_points.shape[-4]
    pts = np.asarray(s.points).reshape(f, -1, 3) - np.asarray(facets.translations)[:, None, :]
    areas = np.asarray(s.areas).reshape(f, -1)
    out = []
    for p, w in zip(pts, areas, strict=True):
        x, y = p[:, 0] - p[:, 0].mean(), p[:, 1] - p[:, 1].mean()
        a = np.stack([np.ones_like(x), x, y, x**2 + y**2], -1) * np.sqrt(w)[:, None]
        c = np.linalg.lstsq(a, p[:, 2] * np.sqrt(w), rcond=None)[0]
        out.append({"focal_length_m": float(1.0 / (4.0 * c[3])), "tilt_mrad": [float(c[1] * 1e3), float(c[2] * 1e3)]})
    return out


def records_figure(reconstruction: RecordsReconstruction, records: FluxRecords):
    """Per record: measured image and every traced surface (6 x 6 m windows, each
    scaled to its maximum), with NCC and KL; the loss curve below."""
    plt = pyplot()
    names = list(reconstruction.traced)
    n = len(reconstruction.record_ids)
    fig = plt.figure(figsize=(3.2 * (len(names) + 1) + 0.8, 3.1 * n + 2.6), layout="constrained")
    grid = fig.add_gridspec(n + 1, len(names) + 1, height_ratios=[1.0] * n + [0.75])
    im, image_axes = None, []
    for i, rid in enumerate(reconstruction.record_ids):
        role = "train" if i in reconstruction.train else "held out"
        panels = [("measured", np.asarray(records.images[i]), "")] + [
            (
                name,
                reconstruction.traced[name][i],
                f"\nNCC {reconstruction.ncc[name][i]:.3f}, KL {reconstruction.kl[name][i]:.3f}",
            )
            for name in names
        ]
        for j, (name, img, extra) in enumerate(panels):
            ax = fig.add_subplot(grid[i, j])
            image_axes.append(ax)
            im = ax.imshow(
                img / max(float(img.max()), 1e-300), extent=(-3.0, 3.0, -3.0, 3.0), cmap="inferno", vmin=0, vmax=1
            )
            ax.set_title(f"{reconstruction.heliostat_id} {rid} ({role}): {name}{extra}", fontsize=8)
            ax.set_xlabel("u, along the target [m]", fontsize=8)
            ax.set_ylabel("v, up [m]", fontsize=8)
    if im is not None:
        fig.colorbar(im, ax=image_axes, label="relative brightness (max = 1)", shrink=0.6)
    ax = fig.add_subplot(grid[n, :])
    losses = reconstruction.result.losses
    ax.semilogy(np.arange(1, len(losses) + 1), losses, label="relative flux mismatch + regularisation")
    ax.set_xlabel("optimiser step")
    ax.set_ylabel("loss")
    ax.set_title("reconstruction loss on the training records", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return fig


__all__ = [
    "RecordsReconstruction",
    "low_order_shape",
    "normal_deviation_map",
    "normal_deviation_mrad",
    "reconstruct_from_records",
    "records_figure",
]
