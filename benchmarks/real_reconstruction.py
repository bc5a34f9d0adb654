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

import numpy as np  # noqa: E402

from heliojax._errors import ConfigError  # noqa: E402
from heliojax.cli._common import check_output_paths, integer, number  # noqa: E402
from heliojax.optics import (  # noqa: E402
    BuieSun,
    flux_records,
    flux_sample_records,
    low_order_shape,
    normal_deviation_map,
    normal_deviation_mrad,
    reconstruct_from_records,
    scene_from_artist,
)

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[1] / "shared" / "data"
SUN = BuieSun(0.05)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--paint", type=Path, default=SHARED / "paint")
    ap.add_argument(
        "--scenario", type=Path, default=SHARED / "artist-scenarios" / "paint_four_heliostats_deflectometry.h5"
    )
    ap.add_argument("--steps", type=integer(1), default=300)
    ap.add_argument("--learning-rate", type=number(0.0, above=True), default=5e-5)
    ap.add_argument("--smoothness", type=number(0.0), default=1e-2)
    ap.add_argument("--n-ctrl", type=integer(1), default=8)
    ap.add_argument("--heliostats", nargs="*", default=None)
    ap.add_argument(
        "--figure", type=Path, default=None, help="held-out images: measured, ideal, reconstructed, deflectometry"
    )
    ap.add_argument(
        "--maps", type=Path, default=None, help="maps of the normal deviation from the deflectometry surface"
    )
    args = ap.parse_args()
    try:  # before the work: a folder or an unwritable place named as the output had failed after it
        check_output_paths(args, ("figure", "maps"))
    except ConfigError as e:
        ap.error(str(e))

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
        for test in range(len(recs.record_ids)):
            train = [k for k in range(len(recs.record_ids)) if k != test]
            t0 = time.perf_counter()
            rec = reconstruct_from_records(
                recs,
                train,
                key=jax.random.key(test),
                references={"deflectometry": measured_facets},
                sunshape=SUN,
                n_ctrl=args.n_ctrl,
                steps=args.steps,
                learning_rate=args.learning_rate,
                smoothness=args.smoothness,
                evaluation_rays=64,
            )
            row = {
                "heliostat": h,
                "held_out_record": recs.record_ids[test],
                "train_records": [recs.record_ids[k] for k in train],
            }
            row["seconds"] = round(time.perf_counter() - t0, 1)
            row["loss_first_last"] = rec.summary()["loss_first_last"]
            for name in rec.traced:
                row[f"held_out_ncc_{name}"] = float(rec.ncc[name][test])
                row[f"held_out_kl_{name}"] = float(rec.kl[name][test])
            row["normal_rms_vs_deflectometry_mrad"] = {
                "ideal": normal_deviation_mrad(rec.ideal, measured_facets),
                "reconstructed": normal_deviation_mrad(rec.result.facets, measured_facets),
            }
            row["low_order"] = {
                name: low_order_shape(f)
                for name, f in (
                    ("ideal", rec.ideal),
                    ("reconstructed", rec.result.facets),
                    ("deflectometry", measured_facets),
                )
            }
            results.append(row)
            panels.append(
                (
                    h,
                    recs.record_ids[test],
                    np.asarray(recs.images[test]),
                    {k: v[test] for k, v in rec.traced.items()},
                    row,
                )
            )
            if test == 0:
                where, ang_ideal, _ = normal_deviation_map(rec.ideal, measured_facets)
                _, ang_rec, _ = normal_deviation_map(rec.result.facets, measured_facets)
                maps.append((h, row["train_records"], where, {"ideal": ang_ideal, "reconstructed": ang_rec}))
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
    from heliojax._plotting import pyplot, save_figure

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
    save_figure(fig, path, dpi=80)  # atomically: an interrupted run leaves no half-written PNG


def deviation_maps(maps, path: Path) -> None:
    from heliojax._plotting import pyplot, save_figure

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
    save_figure(fig, path, dpi=80)


if __name__ == "__main__":
    main()
