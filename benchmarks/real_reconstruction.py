"""Surface reconstruction from PAINT's real flux images, judged on a held-out image
and against the heliostat's deflectometry surface.

For each heliostat with flux images (AA31: 2, AA39: 3, AC43: 2), leave one image
out: reconstruct the NURBS control-point heights (8 x 8 per facet, from ideal
canted facets) from the other images by gradient descent through the tracer
(relative brightness; poses from the records' motor counts turned onto their
measured focal spots), then

* trace the held-out record with the ideal, reconstructed and deflectometry
  surfaces and compare with its measured image (NCC, KL divergence);
* compare the reconstructed and ideal surfaces with the deflectometry surface
  (ARTIST's NURBS fit to PAINT deflectometry): area-weighted RMS normal deviation
  (mrad), and per facet the low-order shape of a fitted paraboloid
  ``z = c0 + c1 x + c2 y + c3 (x^2 + y^2)``: focal length ``1 / (4 c3)`` (m) and
  canting tilt ``(c1, c2)`` (mrad).

    python benchmarks/real_reconstruction.py [--steps 300] [--figure real_reconstruction.png]

Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from heliojax.optics import (  # noqa: E402
    BuieSun,
    NurbsFacets,
    flux_images,
    flux_records,
    flux_sample_records,
    kl_divergence,
    normalised_cross_correlation,
    reconstruct_surface,
    scene_from_artist,
)

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[1] / "shared" / "data"
SUN = BuieSun(0.05)


def trace(surface, recs, key, rays=256):
    n = recs.images.shape[0]
    surfs = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), surface)
    return np.asarray(
        flux_images(
            key, surfs, recs.poses, recs.suns, recs.targets, recs.grids, SUN, rays_per_point=rays // 4, steps=4
        ),
        np.float64,
    )


def normal_angles_mrad(facets: NurbsFacets, reference_points, reference_normals) -> np.ndarray:
    """Angle (mrad) between ``facets``' normals at the reference points' facet-local
    (x, y) and the reference normals, ``(f, p)``."""
    n = np.asarray(facets.normals_at(jnp.asarray(reference_points[..., :2])))
    cross = np.linalg.norm(np.cross(n, reference_normals), axis=-1)
    return np.arctan2(cross, np.sum(n * reference_normals, axis=-1)) * 1e3


def normal_deviation_mrad(facets: NurbsFacets, reference_points, reference_normals, reference_areas) -> float:
    """Area-weighted RMS of :func:`normal_angles_mrad`."""
    ang = normal_angles_mrad(facets, reference_points, reference_normals)
    return float(np.sqrt(np.sum(reference_areas * ang**2) / np.sum(reference_areas)))


def low_order(points, areas) -> list[dict]:
    """Per facet: paraboloid fit -> focal length (m) and tilt (mrad)."""
    out = []
    for p, w in zip(points, areas, strict=True):
        x, y, z = p[:, 0] - p[:, 0].mean(), p[:, 1] - p[:, 1].mean(), p[:, 2]
        a = np.stack([np.ones_like(x), x, y, x**2 + y**2], -1) * np.sqrt(w)[:, None]
        c = np.linalg.lstsq(a, z * np.sqrt(w), rcond=None)[0]
        out.append({"focal_length_m": float(1.0 / (4.0 * c[3])), "tilt_mrad": [float(c[1] * 1e3), float(c[2] * 1e3)]})
    return out


def facet_samples(facets: NurbsFacets, resolution=(24, 24)):
    """Facet-local points, normals, areas ``(f, m*k, ...)``."""
    s = facets.evaluate(resolution)
    f = facets.control_points.shape[-4]
    pts = np.asarray(s.points).reshape(f, -1, 3) - np.asarray(facets.translations)[:, None, :]
    return pts, np.asarray(s.normals).reshape(f, -1, 3), np.asarray(s.areas).reshape(f, -1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--paint", type=Path, default=SHARED / "paint")
    ap.add_argument(
        "--scenario", type=Path, default=SHARED / "artist-scenarios" / "paint_four_heliostats_deflectometry.h5"
    )
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--learning-rate", type=float, default=5e-5)
    ap.add_argument("--smoothness", type=float, default=1e-2)
    ap.add_argument("--n-ctrl", type=int, default=8)
    ap.add_argument("--heliostats", nargs="*", default=None)
    ap.add_argument(
        "--figure", type=Path, default=None, help="held-out images: measured, ideal, reconstructed, deflectometry"
    )
    ap.add_argument(
        "--maps", type=Path, default=None, help="maps of the normal deviation from the deflectometry surface"
    )
    args = ap.parse_args()

    scene = scene_from_artist(args.scenario)
    tower = next(args.paint.glob("*-tower-measurements.json"))
    pairs = flux_sample_records(args.paint / "flux-samples")
    by_heliostat: dict[str, list] = {}
    for rec, props in pairs:
        by_heliostat.setdefault(props.parent.parent.name, []).append((rec, props))
    results, panels, maps = [], [], []
    for h, recs_h in sorted(by_heliostat.items()):
        if args.heliostats and h not in args.heliostats:
            continue
        recs = flux_records(recs_h, tower)
        i = scene.index(h)
        measured_facets = jax.tree.map(lambda x, i=i: x[i], scene.facets)
        ref_pts, ref_nrm, ref_area = facet_samples(measured_facets)
        ideal = NurbsFacets.ideal(recs.layout, n_ctrl=(args.n_ctrl, args.n_ctrl))
        for test in range(len(recs.record_ids)):
            train = [k for k in range(len(recs.record_ids)) if k != test]
            t0 = time.perf_counter()
            result = reconstruct_surface(
                jax.random.key(test),
                ideal,
                recs.subset(train).images,
                recs.subset(train).poses,
                recs.subset(train).suns,
                recs.subset(train).targets,
                recs.subset(train).grids,
                SUN,
                steps=args.steps,
                learning_rate=args.learning_rate,
                smoothness=args.smoothness,
                resolution=(16, 16),
                rays_per_point=32,
                relative=True,
            )
            seconds = time.perf_counter() - t0
            held = recs.subset([test])
            key = jax.random.key(99)
            row = {
                "heliostat": h,
                "held_out_record": held.record_ids[0],
                "train_records": [recs.record_ids[k] for k in train],
            }
            row["seconds"] = round(seconds, 1)
            row["loss_first_last"] = [float(result.losses[:10].mean()), float(result.losses[-10:].mean())]
            images = {}
            for name, facets in (
                ("ideal", ideal),
                ("reconstructed", result.facets),
                ("deflectometry", measured_facets),
            ):
                img = trace(facets.evaluate((24, 24)), held, key)[0]
                images[name] = img
                row[f"held_out_ncc_{name}"] = normalised_cross_correlation(img, held.images[0])
                row[f"held_out_kl_{name}"] = kl_divergence(held.images[0], img)
            row["normal_rms_vs_deflectometry_mrad"] = {
                "ideal": normal_deviation_mrad(ideal, ref_pts, ref_nrm, ref_area),
                "reconstructed": normal_deviation_mrad(result.facets, ref_pts, ref_nrm, ref_area),
            }
            row["low_order"] = {
                name: low_order(*(lambda p, n, a: (p, a))(*facet_samples(f)))
                for name, f in (("ideal", ideal), ("reconstructed", result.facets), ("deflectometry", measured_facets))
            }
            results.append(row)
            panels.append((h, held.record_ids[0], held.images[0], images, row))
            if test == 0:
                where = ref_pts + np.asarray(measured_facets.translations)[:, None, :]
                maps.append(
                    (
                        h,
                        row["train_records"],
                        where,
                        {
                            "ideal": normal_angles_mrad(ideal, ref_pts, ref_nrm),
                            "reconstructed": normal_angles_mrad(result.facets, ref_pts, ref_nrm),
                        },
                    )
                )
            print(json.dumps({k: row[k] for k in row if k != "low_order"}), flush=True)
    summary = {
        "folds": len(results),
        "reconstructed_closer_to_deflectometry": sum(
            r["normal_rms_vs_deflectometry_mrad"]["reconstructed"] < r["normal_rms_vs_deflectometry_mrad"]["ideal"]
            for r in results
        ),
        "held_out_ncc_at_least_ideal": sum(r["held_out_ncc_reconstructed"] >= r["held_out_ncc_ideal"] for r in results),
        "held_out_kl_at_most_ideal": sum(r["held_out_kl_reconstructed"] <= r["held_out_kl_ideal"] for r in results),
        "settings": vars(args) | {"paint": str(args.paint), "scenario": str(args.scenario), "figure": str(args.figure)},
    }
    print(json.dumps({"summary": summary, "folds": results}, indent=1, default=str))
    if args.figure is not None:
        figure(panels, args.figure)
    if args.maps is not None:
        deviation_maps(maps, args.maps)


def figure(panels, path: Path) -> None:
    from heliojax._plotting import pyplot

    plt = pyplot()
    fig, axes = plt.subplots(len(panels), 4, figsize=(13, 3.1 * len(panels)), layout="constrained", squeeze=False)
    for row, (h, rid, measured, images, stats) in zip(axes, panels, strict=True):
        shown = [("measured (held out)", measured, "")] + [
            (name, img, f"\nNCC {stats[f'held_out_ncc_{name}']:.3f}, KL {stats[f'held_out_kl_{name}']:.3f}")
            for name, img in images.items()
        ]
        for ax, (title, img, extra) in zip(row, shown, strict=True):
            im = ax.imshow(img / max(float(img.max()), 1e-300), extent=[-3, 3, -3, 3], cmap="inferno", vmin=0, vmax=1)
            ax.set_title(f"{h} {rid}: {title}{extra}", fontsize=9)
            ax.set_xlabel("u, along the target [m]")
            ax.set_ylabel("v, up [m]")
        fig.colorbar(im, ax=row, label="relative brightness (max = 1)", shrink=0.9)
    fig.savefig(path, dpi=80)


def deviation_maps(maps, path: Path) -> None:
    from heliojax._plotting import pyplot

    plt = pyplot()
    fig, axes = plt.subplots(len(maps), 2, figsize=(9.5, 3.3 * len(maps)), layout="constrained", squeeze=False)
    vmax = max(float(np.percentile(np.concatenate([a.ravel() for m in maps for a in m[3].values()]), 99)), 1e-3)
    for row, (h, train, where, angles) in zip(axes, maps, strict=True):
        for ax, (name, ang) in zip(row, angles.items(), strict=True):
            sc = ax.scatter(
                where[..., 0].ravel(), where[..., 1].ravel(), c=ang.ravel(), s=4, cmap="viridis", vmin=0, vmax=vmax
            )
            rms = np.sqrt(np.mean(ang**2))
            ax.set_title(
                f"{h}, {name} vs deflectometry (RMS over the points {rms:.2f} mrad)\ntrained on {train}", fontsize=9
            )
            ax.set_xlabel("x, east on the mirror [m]")
            ax.set_ylabel("y, north on the mirror [m]")
            ax.set_aspect("equal")
        fig.colorbar(sc, ax=row, label="normal deviation [mrad]", shrink=0.9)
    fig.savefig(path, dpi=80)


if __name__ == "__main__":
    main()
