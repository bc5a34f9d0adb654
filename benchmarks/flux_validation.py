"""Forward validation on PAINT's real flux images: every shared flux image traced
with (a) ideal canted facets and (b) the heliostat's deflectometry surface (ARTIST's
NURBS fit to its PAINT deflectometry), each aligned by the record's motor counts and
turned onto the record's measured focal spot (shape, not aim, is compared), against
the measured ``-flux-centered.png``: normalised cross-correlation, KL divergence and
second-moment widths.

    python benchmarks/flux_validation.py [--paint ../shared/data/paint]
        [--scenario ../shared/data/artist-scenarios/paint_four_heliostats_deflectometry.h5]
        [--figure flux_validation.png]

Prints one JSON object (per image and a summary).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from heliojax._errors import ConfigError  # noqa: E402
from heliojax.cli._common import check_output_paths, integer, number  # noqa: E402
from heliojax.optics import (  # noqa: E402
    BuieSun,
    EffectiveSun,
    compare_record,
    flux_sample_records,
    ideal_surface,
    layout_from_properties,
    scene_from_artist,
)
from heliojax.paint import read_heliostat_properties  # noqa: E402

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[1] / "shared" / "data"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--paint", type=Path, default=SHARED / "paint")
    ap.add_argument(
        "--scenario", type=Path, default=SHARED / "artist-scenarios" / "paint_four_heliostats_deflectometry.h5"
    )
    ap.add_argument("--resolution", type=integer(1), default=32, help="surface points per facet and direction")
    ap.add_argument("--rays", type=integer(1), default=64, help="rays per surface point (x 4 steps)")
    ap.add_argument(
        "--slope-error-mrad", type=number(0.0), default=0.0, help="extra Gaussian slope error of both surfaces"
    )
    ap.add_argument("--figure", type=Path, default=None)
    args = ap.parse_args()
    try:  # before the work: a folder or an unwritable place named as the output had failed after it
        check_output_paths(args, ("figure",))
    except ConfigError as e:
        ap.error(str(e))

    scene = scene_from_artist(args.scenario)
    res = (args.resolution, args.resolution)
    measured_surfaces = scene.facets.evaluate(res)
    sun = BuieSun(0.05)
    if args.slope_error_mrad > 0:
        sun = EffectiveSun(sun, args.slope_error_mrad * 1e-3)
    tower = next(args.paint.glob("*-tower-measurements.json"))
    rows, comparisons = [], []
    for rec, props_path in flux_sample_records(args.paint / "flux-samples"):
        props = read_heliostat_properties(props_path)
        i = scene.index(props.heliostat_id)
        surfaces = {
            "ideal": ideal_surface(layout_from_properties(props), res),
            "deflectometry": jax.tree.map(lambda x, i=i: x[i], measured_surfaces),
        }
        row = {}
        for name, surface in surfaces.items():
            c = compare_record(
                rec,
                props_path,
                tower,
                surface=surface,
                sunshape=sun,
                rays_per_point=args.rays,
                steps=4,
                correct_pointing=True,
            )
            row[name] = c.summary()
            comparisons.append((name, c))
        rows.append({"heliostat": props.heliostat_id, "record": int(rec.name.split("-")[0]), **row})
    better = lambda key, sign: sum(sign * (r["deflectometry"][key] - r["ideal"][key]) > 0 for r in rows)  # noqa: E731
    summary = {
        "images": len(rows),
        "deflectometry_better_ncc": better("ncc_centred", 1),
        "deflectometry_better_kl": better("kl_centred", -1),
        "sun": f"Buie csr 0.05, slope error {args.slope_error_mrad} mrad",
    }
    print(json.dumps({"summary": summary, "images": rows}, indent=1))
    if args.figure is not None:
        figure(comparisons, args.figure)


def figure(comparisons, path: Path) -> None:
    from heliojax._plotting import pyplot, save_figure

    plt = pyplot()
    by_record: dict = {}
    for name, c in comparisons:
        by_record.setdefault((c.heliostat_id, c.record_id), {})[name] = c
    n = len(by_record)
    fig, axes = plt.subplots(n, 3, figsize=(10.5, 3.1 * n), layout="constrained", squeeze=False)
    for row, ((h, r), cs) in zip(axes, sorted(by_record.items()), strict=True):
        panels = (
            ("measured", cs["ideal"].measured_centred, None),
            ("ideal facets", cs["ideal"].traced_centred, cs["ideal"]),
            ("deflectometry", cs["deflectometry"].traced_centred, cs["deflectometry"]),
        )
        for ax, (title, img, c) in zip(row, panels, strict=True):
            img = np.asarray(img) / max(float(np.max(img)), 1e-300)
            im = ax.imshow(img, extent=[-3, 3, -3, 3], origin="upper", cmap="inferno", vmin=0, vmax=1)
            label = f"{h} {r}: {title}"
            if c is not None:
                label += f"\nNCC {c.ncc_centred:.3f}, KL {c.kl_centred:.3f}"
            ax.set_title(label, fontsize=9)
            ax.set_xlabel("u, along the target [m]")
            ax.set_ylabel("v, up [m]")
        fig.colorbar(im, ax=row, label="relative brightness (max = 1)", shrink=0.9)
    save_figure(fig, path, dpi=90)  # atomically: an interrupted run leaves no half-written PNG


if __name__ == "__main__":
    main()
