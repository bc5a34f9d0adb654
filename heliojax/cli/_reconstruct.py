"""``heliojax reconstruct``: recover NURBS control points of a mirror surface from flux
images by gradient descent through the ray tracer (thin over :mod:`heliojax.optics`)."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import typing
from pathlib import Path

from ._common import heliostat_id, integer, number, path_type

log = logging.getLogger(__name__)

EXAMPLES = """examples:
  heliojax reconstruct --out out/reconstruction
  heliojax reconstruct --images 8 --steps 300 --rays-per-point 64 --seed 3 --out out/reconstruction
  heliojax reconstruct --paint ../shared/data/paint/flux-samples --heliostat AA39 --held-out 270398 \
      --scenario ../shared/data/artist-scenarios/paint_four_heliostats_deflectometry.h5 --out out/aa39"""

OUTPUT_FILES = ()
OUTPUT_DIRS = ("out",)
"""Output paths checked before any work (attribute names of the parsed arguments)."""
OUTPUT_NAMES = ("control_points.h5", "reconstruction.png", "reconstruction.json")
"""The files written in ``--out``."""


def outputs_inside(args) -> list[tuple[str, Path]]:
    """The files this command writes in its output directory, checked before any work."""
    return [("out", args.out / name) for name in OUTPUT_NAMES]


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "reconstruct",
        help="gradient-based surface reconstruction from flux images (real PAINT records or a synthetic benchmark)",
        description=(
            "Recover the control-point heights of a heliostat's NURBS facets from several flux "
            "images by Adam through the differentiable ray tracer (fresh rays every step, "
            "smoothness regularisation). With --paint and --heliostat it uses the heliostat's real "
            "flux records (PAINT layout <H>/Calibration/<ID>-flux.png, -flux-centered.png and the "
            "calibration JSON; relative brightness; each record's pose from its motor counts turned "
            "onto its measured focal spot), trains on all records but --held-out and scores every "
            "record (NCC, KL) with the ideal, the reconstructed and, with --scenario, the "
            "deflectometry surface of an ARTIST scenario. A record that cannot be used (a damaged or blank "
            "flux PNG, a malformed record JSON, no focal spot) or has no flux image is left out with a warning "
            "and listed under skipped_records in reconstruction.json. Without --paint it runs the synthetic "
            "benchmark: a hidden surface with 1-3 mrad bumps, imaged for N sun positions. Writes "
            "OUT/reconstruction.json, OUT/control_points.h5 and OUT/reconstruction.png."
        ),
    )
    p.add_argument(
        "--images", type=integer(1, 32), default=6, help="number of flux images (sun positions), 4-8 typical"
    )
    p.add_argument("--seed", type=integer(0, 2**32 - 1), default=1, help="seed of the hidden surface and of the rays")
    p.add_argument("--steps", type=integer(1, 100_000), default=150, help="optimiser steps (>= 1)")
    p.add_argument(
        "--learning-rate",
        type=number(0.0, 1.0, above=True),
        default=None,
        help="Adam step (m of control height); default 2.5e-4 synthetic, 5e-5 real records",
    )
    p.add_argument(
        "--rays-per-point", type=integer(1, 512), default=32, help="rays per surface point per image and step"
    )
    p.add_argument(
        "--smoothness",
        type=number(0.0, 1e6),
        default=None,
        help="weight of the curvature penalty on the control heights (1/m^2); default 1e-3 synthetic, 1e-2 real",
    )
    p.add_argument(
        "--flux-weight", type=number(0.0, 1e6), default=1.0, help="weight of the flux-conservation term (dimensionless)"
    )
    p.add_argument(
        "--paint",
        type=path_type,
        default=None,
        help="PAINT directory with <H>/Calibration flux records (e.g. ../shared/data/paint/flux-samples)",
    )
    p.add_argument(
        "--heliostat", default=None, type=heliostat_id, help="heliostat id of the real records (with --paint)"
    )
    p.add_argument(
        "--tower",
        type=path_type,
        default=None,
        help="tower-measurements JSON (default: the one in --paint or its parent)",
    )
    p.add_argument(
        "--held-out", nargs="*", type=integer(0), default=[], help="record ids kept out of the reconstruction"
    )
    p.add_argument(
        "--scenario",
        type=path_type,
        default=None,
        help="ARTIST scenario HDF5 whose surface of --heliostat is scored too",
    )
    p.add_argument(
        "--n-ctrl", type=integer(4, 32), default=8, help="control points per facet and direction (real mode)"
    )
    p.add_argument("--out", type=path_type, default=Path("reconstruction"), help="output directory")
    p.add_argument("--quiet", action="store_true", help="no progress bar or messages on stderr")


def run(args: argparse.Namespace) -> int:
    import jax
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from .. import optics

    real = args.paint is not None or args.heliostat is not None
    if args.learning_rate is None:
        args.learning_rate = 5e-5 if real else 2.5e-4
    if args.smoothness is None:
        args.smoothness = 1e-2 if real else 1e-3
    if not 1 <= args.images <= 32:
        print("heliojax reconstruct: error: --images must lie in 1..32", file=sys.stderr)
        return 2
    for flag, value, ok in (
        ("--steps", args.steps, args.steps >= 1),
        ("--rays-per-point", args.rays_per_point, args.rays_per_point >= 1),
        ("--learning-rate", args.learning_rate, math.isfinite(args.learning_rate) and args.learning_rate > 0),
        ("--smoothness", args.smoothness, math.isfinite(args.smoothness) and args.smoothness >= 0),
        ("--flux-weight", args.flux_weight, math.isfinite(args.flux_weight) and args.flux_weight >= 0),
    ):
        if not ok:
            print(f"heliojax reconstruct: error: {flag} {value} is out of range (see --help)", file=sys.stderr)
            return 2
    if real:
        return _run_real(args)
    ignored = [
        flag
        for flag, value in (("--tower", args.tower), ("--scenario", args.scenario), ("--held-out", args.held_out))
        if value
    ]
    if ignored:  # the synthetic scene has no tower, scenario or records: it would run as if they were not given
        print(
            f"heliojax reconstruct: error: {', '.join(ignored)}: only with --paint and --heliostat (real records)",
            file=sys.stderr,
        )
        return 2
    scene = optics.synthetic_scene(seed=args.seed, n_images=args.images)
    losses = []
    res = optics.reconstruct_surface(
        jax.random.key(args.seed),
        scene.ideal,
        scene.images,
        scene.poses,
        scene.suns,
        scene.target,
        scene.grid,
        scene.sunshape,
        steps=args.steps,
        learning_rate=args.learning_rate,
        rays_per_point=args.rays_per_point,
        smoothness=args.smoothness,
        flux_weight=args.flux_weight,
        callback=lambda j, loss: losses.append(loss),
    )
    e_ideal = optics.normal_rms_error_mrad(scene.ideal, scene.truth)
    e_rec = optics.normal_rms_error_mrad(res.facets, scene.truth)
    report = {
        "images": args.images,
        "steps": args.steps,
        "normal_rms_error_ideal_mrad": e_ideal,
        "normal_rms_error_recovered_mrad": e_rec,
        "ratio": e_rec / e_ideal,
        "loss_first": float(res.losses[0]),
        "loss_last": float(res.losses[-1]),
    }
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6), layout="constrained")
    true_dz = np.asarray(scene.truth.control_points[..., 2] - scene.ideal.control_points[..., 2])
    lim = np.abs(true_dz).max() * 1e3
    for a, d, t in ((ax[0], true_dz, "hidden height offsets"), (ax[1], res.dz, "recovered height offsets")):
        tiles = np.block([[d[2].T[::-1], d[3].T[::-1]], [d[0].T[::-1], d[1].T[::-1]]]) * 1e3
        im = a.imshow(tiles, cmap="coolwarm", vmin=-lim, vmax=lim)
        a.set_title(f"{t}\n(4 facets, 2 x 2 as seen from the target)", fontsize=10)
        a.set_xlabel("control point along the mirror width (index)")
        a.set_ylabel("control point along the height (index)")
        fig.colorbar(im, ax=a, label="control-point height offset [mm]", shrink=0.85)
    ax[2].semilogy(np.arange(1, len(res.losses) + 1), res.losses, label="flux-matching loss")
    ax[2].set_xlabel("optimiser step")
    ax[2].set_ylabel("loss (relative flux mismatch + regularisation)")
    ax[2].set_title(f"normal RMS error vs truth: ideal {e_ideal:.2f} -> recovered {e_rec:.2f} mrad", fontsize=10)
    ax[2].legend(fontsize=8)
    ax[2].grid(alpha=0.3, which="both")
    _write_outputs(
        args.out, res.facets, fig, report, res.losses, extra={"true_control_points": scene.truth.control_points}
    )
    return 0


def _run_real(args: argparse.Namespace) -> int:
    """Reconstruction from a heliostat's real flux records."""
    import jax

    from .. import optics
    from .._errors import DataError, one_line
    from ..paint import read_artist_scenario

    def fail(message: str) -> int:
        print(f"heliojax reconstruct: error: {message}", file=sys.stderr)
        return 2

    if args.paint is None or args.heliostat is None:
        return fail("real records need both --paint DIR and --heliostat ID")
    pairs = [p for p in optics.flux_sample_records(args.paint) if p[1].parent.parent.name == args.heliostat]
    # records of the heliostat without a flux image: not flux records, but the user should hear of them
    no_image = _records_without_flux(args.paint / args.heliostat / "Calibration")
    if no_image:
        log.warning(
            f"{len(no_image)} record(s) of {args.heliostat} have no flux image ({', '.join(no_image[:5])}"
            f"{' ...' if len(no_image) > 5 else ''}: <ID>-flux.png missing); they are left out"
        )
    if not pairs:
        found = sorted({p[1].parent.parent.name for p in optics.flux_sample_records(args.paint)})
        some = ", ".join(found) or "none"
        why = f" ({len(no_image)} record(s) without a flux image)" if no_image else ""
        get = (
            ""
            if found
            else "; `heliojax fetch --out DIR --heliostats ID --assets calibration_properties,flux_image` "
            "downloads records with their flux images from PAINT"
        )
        return fail(f"no flux records of {args.heliostat}{why} under {args.paint} (heliostats with some: {some}){get}")
    tower = args.tower
    if tower is None:
        candidates = [
            *args.paint.glob("*-tower-measurements.json"),
            *args.paint.parent.glob("*-tower-measurements.json"),
        ]
        if not candidates:
            return fail(f"no *-tower-measurements.json in {args.paint} or its parent: pass --tower")
        tower = candidates[0]
    try:
        records = optics.flux_records(pairs, tower, skip_bad=True)
        references = {}
        if args.scenario is not None:
            # a damaged heliostat of the scenario spoils only itself
            scenario = read_artist_scenario(args.scenario, skip_bad=True)
            damaged = dict(scenario.skipped)
            if args.heliostat in damaged:
                return fail(f"--scenario: heliostat {args.heliostat} is damaged there: {damaged[args.heliostat]}")
            for name, reason in scenario.skipped:
                log.warning(f"--scenario: heliostat {name} left out (damaged: {one_line(reason, 200)})")
            scene = optics.scene_from_artist(scenario)
            i = scene.index(args.heliostat)
            references["deflectometry"] = jax.tree_util.tree_map(lambda x: x[i], scene.facets)
    except (DataError, KeyError) as e:
        return fail(str(e))
    skipped = dict(records.skipped)
    for rid in args.held_out:  # a record the user asked to score must be scored, or the reason given
        if str(rid) in skipped:
            return fail(f"--held-out {rid}: the record cannot be used: {skipped[str(rid)]}")
        if str(rid) in no_image:
            return fail(
                f"--held-out {rid}: record {rid} of {args.heliostat} has no flux image ({rid}-flux.png missing)"
            )
    unknown = sorted(set(args.held_out) - set(records.record_ids))
    if unknown:
        return fail(
            f"--held-out {unknown}: not records of {args.heliostat} ({', '.join(map(str, records.record_ids))})"
        )
    train = [i for i, r in enumerate(records.record_ids) if r not in set(args.held_out)]
    if not train:
        return fail("every record is held out: nothing to reconstruct from")
    rec = optics.reconstruct_from_records(
        records,
        train,
        key=jax.random.key(args.seed),
        references=references,
        n_ctrl=args.n_ctrl,
        steps=args.steps,
        learning_rate=args.learning_rate,
        smoothness=args.smoothness,
        rays_per_point=args.rays_per_point,
    )
    report = rec.summary()
    as_id = lambda r: int(r) if r.isdecimal() else r  # noqa: E731 (a file name when its id is unreadable)
    report["skipped_records"] = [{"record": as_id(r), "reason": why} for r, why in records.skipped] + [
        {"record": as_id(r), "reason": f"no flux image ({r}-flux.png missing)"} for r in no_image
    ]
    if "deflectometry" in references:
        report["normal_rms_vs_deflectometry_mrad"] = {
            name: optics.normal_deviation_mrad(f, references["deflectometry"])
            for name, f in (("ideal", rec.ideal), ("reconstructed", rec.result.facets))
        }
    attrs = {"heliostat": args.heliostat, "train_records": [records.record_ids[i] for i in rec.train]}
    figure = optics.records_figure(rec, records)
    _write_outputs(args.out, rec.result.facets, figure, report, rec.result.losses, attrs=attrs)
    return 0


def _records_without_flux(calibration: Path) -> list[str]:
    """IDs of the calibration records in ``calibration`` (``<ID>-calibration-properties.json``)
    that have no ``<ID>-flux.png``, sorted."""
    suffix = "-calibration-properties.json"
    return sorted(
        p.name[: -len(suffix)]
        for p in calibration.glob(f"*{suffix}")
        if not (calibration / p.name.replace(suffix, "-flux.png")).exists()
    )


def _loss_rose(losses) -> tuple[float, float] | None:
    """``(first, last)`` mean loss over the first and the last ``k`` steps (``k`` from
    :func:`heliojax.optics.loss_window`, a fifth of the steps, 1 to 10: the loss of one
    step is a draw of rays; the same window as ``loss_first_last`` in the report) where
    the last is above the first: the optimiser made the surface worse than where it
    started; else None."""
    import numpy as np

    from ..optics import loss_window

    x = np.asarray(losses, float)
    k = loss_window(x.size)
    first, last = float(x[:k].mean()), float(x[-k:].mean())
    return (first, last) if x.size > 1 and last > first else None


def _write_outputs(out: Path, facets, fig, report: dict, losses, *, extra=None, attrs=None) -> None:
    """OUT/control_points.h5 (the facets' control points, translations, degree, plus
    ``extra`` datasets and ``attrs``), OUT/reconstruction.png and OUT/reconstruction.json
    (also printed), each written atomically. ``losses``: the loss per step; a loss that
    rose (:func:`_loss_rose`) is a warning and ``"diverged": true`` in the JSON."""
    import matplotlib.pyplot as plt
    import numpy as np

    from .._errors import ConfigError
    from .._io import atomic_h5, atomic_path, atomic_write, staged_paths

    rose = _loss_rose(losses)
    report["diverged"] = rose is not None
    if rose is not None:
        log.warning(
            f"the loss rose from {rose[0]:.4g} to {rose[1]:.4g} over {len(losses)} steps: the optimiser diverged and "
            "the surface written is worse than the one it started from; lower --learning-rate"
        )
    bad = _non_finite(report)
    if bad or not np.isfinite(np.asarray(facets.control_points)).all():
        raise ConfigError(
            f"the reconstruction diverged ({', '.join(bad[:3]) or 'control points'} not finite): "
            "lower --learning-rate or --flux-weight; nothing written"
        )
    # published together: a run stopped while writing leaves the previous set as it was
    with staged_paths([out / "control_points.h5", out / "reconstruction.png", out / "reconstruction.json"]) as temps:
        h5_path, png_path, json_path = typing.cast(list[Path], temps)
        with atomic_h5(h5_path) as f:
            f.create_dataset("control_points", data=np.asarray(facets.control_points))
            f.create_dataset("translations", data=np.asarray(facets.translations))
            for name, value in (extra or {}).items():
                f.create_dataset(name, data=np.asarray(value))
            f.attrs["degree"] = facets.degree
            for name, value in (attrs or {}).items():
                f.attrs[name] = value
        with atomic_path(png_path) as tmp:
            fig.savefig(tmp, dpi=90, format="png", bbox_inches="tight")
        plt.close(fig)
        with atomic_write(json_path) as f:
            json.dump(report, f, indent=2)
    print(json.dumps(report, indent=2))


def _non_finite(value, where: str = "") -> list[str]:
    """Paths (``a.b[2]``) of the NaN / inf numbers in a JSON-able ``value``."""
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _non_finite(v, f"{where}.{k}" if where else str(k))]
    if isinstance(value, list | tuple):
        return [p for i, v in enumerate(value) for p in _non_finite(v, f"{where}[{i}]")]
    if isinstance(value, float) and not math.isfinite(value):
        return [where]
    return []
