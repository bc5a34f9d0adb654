"""``heliojax trace``: flux image of a heliostat for a calibration record or a sun position
(thin over :mod:`heliojax.optics`)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import typing
from pathlib import Path

from ._common import (
    check_sun_possible,
    heliostat_id,
    integer,
    number,
    option_label,
    path_type,
    target_name,
    warn_moved,
)

log = logging.getLogger(__name__)

MAX_MRAD = 100.0
"""Largest --sigma-mrad and --slope-error-mrad: 100 mrad (5.7 degrees) per axis is already
no sun or mirror (the sun's disc has a half-angle of 4.65 mrad); beyond, every ray misses."""

DEFAULT_CSR = 0.05
"""Default Buie circumsolar ratio (a clear day)."""

DEFAULT_SIGMA_MRAD = 2.51
"""Default Gaussian sun sigma per axis, mrad (the value this command has always used; a uniform
disc of the sun's 4.65 mrad radius has 2.33 per axis, the circumsolar aureole widens it)."""


EXAMPLES = """examples:
  heliojax trace ../shared/data/paint/flux-samples --heliostat AA39 --record 270398 --out out/trace
  heliojax trace --heliostat BE36 --sun-azimuth -20 --sun-elevation 35 --sunshape pillbox --out out/trace"""

SOLAR_CONSTANT_PERIHELION = 1413.0
"""W/m^2 above the atmosphere at the sun's closest: no DNI on the ground exceeds it."""

OUTPUT_FILES = ()
OUTPUT_DIRS = ("out",)
"""Output paths checked before any work (attribute names of the parsed arguments)."""


DEFAULT_TRACE_TARGET = "solar_tower_juelich_lower"
"""``--target`` of a trace at a sun position when not given."""

OFF_IMAGE_WARNING = 0.5
"""Fraction of the power reflected onto the target's plane that, landing outside the
image (the target's rectangle), is warned about: more than half. A spot is symmetric
about its centre to first order (sun shape and slope errors are), so more than half of
it off the image puts its centre off the image: the image's centroid is then that of a
cut-off tail, at the edge, and its power is not the heliostat's."""


def _tag(args) -> str:
    """The part of the output file names naming the record or the sun."""
    return str(args.record) if args.record is not None else f"az{args.sun_azimuth:g}_el{args.sun_elevation:g}"


def outputs_inside(args) -> list[tuple[str, Path]]:
    """The files this command writes in ``--out``, checked before any work (none while
    the record / sun flags are incomplete: :func:`run` names that error)."""
    if args.heliostat is None or (args.record is None and (args.sun_azimuth is None or args.sun_elevation is None)):
        return []
    return [("out", _output(args, kind)) for kind in ("flux.h5", "flux.png", "comparison.png", "summary.json")]


def _output(args, kind: str) -> Path:
    """The output file ``kind`` (``flux.h5``, ``flux.png``, ``comparison.png``, ``summary.json``) in ``--out``."""
    return args.out / f"{args.heliostat}-{_tag(args)}-{kind}"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "trace",
        help="ray-trace a heliostat's flux image onto a target (PNG + HDF5)",
        description=(
            "Align a heliostat (PAINT properties; nominal linear-actuator kinematics, or the "
            "calibrated ones of --results) with the motor "
            "counts of a calibration record (--record) or aim it at a target for a given sun "
            "(--sun-azimuth/--sun-elevation), trace its flux onto the target plane and write "
            "OUT/<H>-<ID or sun>-flux.png and .h5 (W/m^2, extent in metres). With --record and "
            "the record's measured flux PNGs beside it, a comparison (centroid distance, "
            "normalised cross-correlation) is written too."
        ),
    )
    p.add_argument(
        "paint",
        type=path_type,
        nargs="?",
        default=None,
        metavar="PAINT_DIR",
        help="PAINT-layout directory (<H>/Properties, <H>/Calibration; default: the embedded real subset)",
    )
    p.add_argument(
        "--heliostat",
        default=None,
        type=heliostat_id,
        help="heliostat id, e.g. BE36 of the embedded data (required; or `heliostat` in --config)",
    )
    p.add_argument("--record", type=integer(0), help="calibration record id (counts, sun and target of the record)")
    p.add_argument(
        "--sun-azimuth", type=number(-360.0, 360.0), help="sun azimuth in degrees, 0 = south, positive toward east"
    )
    p.add_argument(
        "--sun-elevation", type=number(0.0, 90.0, above=True), help="sun elevation in degrees above the horizon (> 0)"
    )
    p.add_argument(
        "--target",
        type=target_name,
        default=None,
        help=f"target name with --sun-* (aimed at its centre; default {DEFAULT_TRACE_TARGET}); with --record "
        "the record's target",
    )
    p.add_argument("--tower", type=path_type, help="tower file (default: PAINT_DIR's or its parent's)")
    p.add_argument("--deflectometry", type=path_type, help="PAINT deflectometry HDF5: fit NURBS facets to it")
    p.add_argument(
        "--results",
        type=path_type,
        metavar="FILE",
        help="results.h5 of `heliojax calibrate`: trace with the heliostat's calibrated model and geometry "
        "(default: nominal linear-actuator kinematics)",
    )
    p.add_argument(
        "--sunshape", choices=("buie", "gaussian", "pillbox"), default="buie", help="sun shape of the ray directions"
    )
    p.add_argument(
        "--csr",
        type=number(0.0, 1.0, above=True, below=True),
        default=None,
        help=f"Buie circumsolar ratio in (0, 1), --sunshape buie only (default {DEFAULT_CSR:g})",
    )
    p.add_argument(
        "--sigma-mrad",
        type=number(0.0, MAX_MRAD, above=True),
        default=None,
        help=f"Gaussian sun sigma per axis, mrad, --sunshape gaussian only (default {DEFAULT_SIGMA_MRAD:g}; "
        f"the sun's disc is 4.65; at most {MAX_MRAD:g})",
    )
    p.add_argument(
        "--slope-error-mrad",
        type=number(0.0, MAX_MRAD),
        default=1.5,
        help=f"Gaussian mirror slope error per axis, mrad (0: none; at most {MAX_MRAD:g})",
    )
    p.add_argument(
        "--rays-per-point", type=integer(1, 2**16), default=64, help="rays per surface point and chunk (>= 1)"
    )
    p.add_argument(
        "--steps", type=integer(1, 10_000), default=4, help="lax.scan chunks (rays per point = rays-per-point x steps)"
    )
    p.add_argument("--resolution", type=integer(2, 4096), default=32, help="surface points per facet edge")
    p.add_argument(
        "--pixels",
        type=integer(8, 4096),
        default=256,
        help="image pixels per side (8-4096; the bilinear splat loses the flux within half a pixel of the image's "
        "edge, so coarse images undercount the power of a spot that reaches the edge)",
    )
    p.add_argument(
        "--dni",
        type=number(0.0, SOLAR_CONSTANT_PERIHELION, above=True),
        default=1000.0,
        help=f"direct normal irradiance, W/m^2 (at most {SOLAR_CONSTANT_PERIHELION:g}, the sun's above the air)",
    )
    p.add_argument(
        "--reflectivity", type=number(0.0, 1.0, above=True), default=1.0, help="mirror reflectivity in (0, 1]"
    )
    p.add_argument("--seed", type=integer(0, 2**32 - 1), default=0, help="seed of the ray sampling")
    p.add_argument("--out", type=path_type, default=Path("trace"), help="output directory")
    p.add_argument("--quiet", action="store_true", help="no messages on stderr (the summary still goes to stdout)")


def _tower_path(args) -> Path:
    if args.tower is not None:
        return args.tower
    for d in (args.paint, args.paint.parent):
        found = sorted(d.glob("*tower-measurements.json"))
        if found:
            return found[0]
    raise FileNotFoundError(f"no *tower-measurements.json in {args.paint} or its parent; pass --tower")


MAX_RAYS_PER_FACET = 2**24
"""Largest --resolution squared x --rays-per-point: rays per facet traced at once (held in
memory; the defaults trace 2**16)."""


def run(args: argparse.Namespace) -> int:
    import jax
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from .. import optics
    from .._errors import ConfigError, HeliojaxError, few_names
    from .._geometry import sun_direction
    from .._io import atomic_h5, atomic_path, json_safe, staged_paths, write_json
    from .._kinematics import ActuatorModel, forward, inverse_aim
    from .._progress import progress_bar
    from ..paint import TIMESTAMPS_FILE, read_calibration_record, read_heliostat_properties, read_timestamps, read_tower

    if args.heliostat is None:
        raise ConfigError("--heliostat is required (on the command line, or `heliostat` in the --config's [trace])")
    for dest, flag, shape in (("csr", "--csr", "buie"), ("sigma_mrad", "--sigma-mrad", "gaussian")):
        if getattr(args, dest) is not None and args.sunshape != shape:  # another sun shape's: would be ignored
            raise ConfigError(
                f"{option_label(args, dest, flag)} applies to --sunshape {shape} only, not to "
                f"{option_label(args, 'sunshape', '--sunshape')} {args.sunshape}"
            )
    if (args.record is None) == (args.sun_azimuth is None or args.sun_elevation is None):
        raise ConfigError("give either --record or both --sun-azimuth and --sun-elevation")
    csr = DEFAULT_CSR if args.csr is None else args.csr
    sigma_mrad = DEFAULT_SIGMA_MRAD if args.sigma_mrad is None else args.sigma_mrad
    per_chunk = args.resolution**2 * args.rays_per_point
    if per_chunk > MAX_RAYS_PER_FACET:  # before any work: the chunk would not fit in memory
        raise ConfigError(
            f"--resolution {args.resolution} and --rays-per-point {args.rays_per_point}: "
            f"{per_chunk:.3g} rays per facet and step; at most {MAX_RAYS_PER_FACET:.3g}"
        )
    tag = _tag(args)
    try:
        if args.paint is None:
            from ..paint import default_data_dir

            args.paint = default_data_dir()
        tower_path = _tower_path(args)
        tower = read_tower(tower_path)
        if args.record is None:  # a record's sun is measured
            check_sun_possible(args.sun_azimuth, args.sun_elevation, tower.origin_lla[0])
        hdir = args.paint / args.heliostat
        props_path = hdir / "Properties" / f"{args.heliostat}-heliostat-properties.json"
        if not props_path.exists():  # name those there are, not only the file that is not
            there = sorted(p.parent.parent.name for p in args.paint.glob("*/Properties/*-heliostat-properties.json"))
            raise ConfigError(
                f"--heliostat {args.heliostat}: no {props_path.relative_to(args.paint)} in {args.paint}; "
                + (f"its heliostats: {few_names(there, 12)}" if there else "it holds no heliostat properties file")
            )
        props = read_heliostat_properties(props_path)
        geometry = optics.geometry_from_properties(props, tower.origin_lla)
        layout = optics.layout_from_properties(props)
        model = ActuatorModel.nominal(jnp.float64)
        if args.results is not None:
            from .._results import load_results

            results = load_results(args.results)
            if args.heliostat not in results.ids:
                raise ConfigError(f"--results {args.results}: no heliostat {args.heliostat!r} in it")
            i = results.ids.index(args.heliostat)
            if not results.fitted[i]:  # its model is the nominal start or a diverged fit: no calibration
                why = results.flags.get(args.heliostat) or (
                    "worse than nominal" if results.worse_than_nominal[i] else results.status[i]
                )
                raise ConfigError(f"--results {args.results}: {args.heliostat} has no usable fit ({why})")
            warn_moved(
                f"{props_path}",
                [args.heliostat],
                geometry.position,
                results,
                "the trace uses the fit's geometry, with this file's facets",
            )
            model, geometry = results.heliostat(args.heliostat)
        if args.deflectometry is not None:
            defl = optics.read_deflectometry(args.deflectometry)
            facets = optics.fit_nurbs(defl, layout.translations[: defl.n_facets])
            surface = facets.evaluate((args.resolution, args.resolution))
        else:
            surface = optics.ideal_surface(layout, (args.resolution, args.resolution))
        base = {
            "buie": lambda: optics.BuieSun(csr),
            "gaussian": lambda: optics.GaussianSun(sigma_mrad * 1e-3),
            "pillbox": lambda: optics.PillboxSun(),
        }[args.sunshape]()
        sunshape = optics.EffectiveSun(base, args.slope_error_mrad * 1e-3) if args.slope_error_mrad > 0 else base
        if args.record is not None:
            rec_path = hdir / "Calibration" / f"{args.record}-calibration-properties.json"
            if not rec_path.is_file():
                have = sorted(
                    (p.name.split("-")[0] for p in (hdir / "Calibration").glob("*-calibration-properties.json")),
                    key=lambda r: (len(r), r),  # numeric order of the ids
                )
                shown = ", ".join(have[:5]) + (f", ... ({len(have)} in all)" if len(have) > 5 else "")
                raise ConfigError(
                    f"--record {args.record}: {args.heliostat} has no such calibration record ({rec_path} "
                    f"not found); its records: {shown or 'none'}"
                )
            # the download's timestamps say whose record it is (a copy under another
            # heliostat's folder is refused, as the loader refuses it)
            stamps = args.paint / TIMESTAMPS_FILE
            timestamps = read_timestamps(stamps, on_error=lambda e: None) if stamps.is_file() else None
            record = read_calibration_record(rec_path, heliostat_id=args.heliostat, timestamps=timestamps)
            az, el, target_name = record.sun_azimuth_deg, record.sun_elevation_deg, record.target_name
            if args.target is not None and args.target != target_name:
                raise ConfigError(
                    f"--target {args.target}: record {args.record} was measured on {target_name}, the target "
                    "its trace is compared with; leave --target out, or trace a sun position (--sun-*) instead"
                )
            counts = jnp.asarray([record.axis_1_counts, record.axis_2_counts], jnp.float64)
        else:
            az, el, target_name = args.sun_azimuth, args.sun_elevation, args.target or DEFAULT_TRACE_TARGET
        target = optics.target_from_tower(tower, target_name)
        sun = sun_direction(jnp.deg2rad(az), jnp.deg2rad(el))  # pyright: ignore[reportArgumentType]
        if args.record is None:
            counts = inverse_aim(model, geometry, target.centre, sun)
        pose = forward(model, geometry, counts)
        grid = optics.ImageGrid.for_target(target, (args.pixels, args.pixels))
        n_rays = optics.ray_count(surface, args.rays_per_point, args.steps)
        log.info(f"tracing {n_rays:,} rays of {args.heliostat} onto {target_name} (the first run compiles the tracer)")
        t0 = time.perf_counter()

        # One call per step (one compiled program, the step index an argument), so that
        # a bar can show progress; the mean of the steps' images is the one-call image.
        def trace(dni: float, reflectivity: float, bar: bool = True) -> np.ndarray:
            image = np.zeros(grid.shape, np.float64)
            key = jax.random.key(args.seed)
            steps = range(args.steps)
            for step in progress_bar(steps, logger=log, desc="tracing", unit="step") if bar else steps:
                image += np.asarray(
                    optics.flux_image(
                        key,
                        surface,
                        pose,
                        sun,
                        target,
                        grid,
                        sunshape,
                        rays_per_point=args.rays_per_point,
                        first_step=jnp.asarray(step, jnp.int32),
                        dni=dni,
                        reflectivity=reflectivity,
                    ),
                    np.float64,
                )
            return image / args.steps

        image = trace(args.dni, args.reflectivity)
        log.info(f"traced in {time.perf_counter() - t0:.1f} s")
        c = np.asarray(optics.centroid(jnp.asarray(image), grid))
        power = float(image.sum() * float(grid.pixel_area))
        on_plane = float(optics.plane_power(surface, pose, sun, target, dni=args.dni, reflectivity=args.reflectivity))
        # the Monte Carlo image may hold a little more than the plane's expectation: clipped
        off_image = min(max(1.0 - power / on_plane, 0.0), 1.0) if on_plane > 0.0 else None
        size = f"{2 * float(target.half_width):.3g} x {2 * float(target.half_height):.3g} m"
        hint = (
            " (nominal kinematics, which can miss by metres: --results of `heliojax calibrate` aims with the "
            "calibrated model)"
            if args.results is None
            else ""
        )
        underflow = None
        if args.dni * args.reflectivity < 1.0 and (off_image is None or off_image > OFF_IMAGE_WARNING):
            # a faint beam's flux density underflows the tracer's float32 (below ~1e-38 W/m^2
            # per ray and pixel; the product of the two options may even be 0.0): traced again
            # at 1 W/m^2, where it cannot, the spot may be on the image after all; then the
            # cause is the irradiance, not the aim
            unit = trace(1.0, 1.0, bar=False)
            unit_on = float(optics.plane_power(surface, pose, sun, target, dni=1.0, reflectivity=1.0))
            unit_off = 1.0 - float(unit.sum() * float(grid.pixel_area)) / unit_on if unit_on > 0.0 else 1.0
            if unit_off <= OFF_IMAGE_WARNING:
                underflow = (
                    f"the flux density underflows the tracer's float32 numbers at --dni {args.dni:g} W/m^2 x "
                    f"--reflectivity {args.reflectivity:g}: traced at 1 W/m^2, {1.0 - max(unit_off, 0.0):.1%} of "
                    f"the reflected power lands on the image ({size}), so the spot is on it; the image, power and "
                    "centroid written are not the spot's. Use a physical --dni (W/m^2, e.g. 1 to 1000)"
                )
        if not power > 0.0:
            # every ray missed the image: why, from the power reflected onto the plane
            # (--dni and --reflectivity are > 0, so they are never the cause, unless they
            # are so small that the flux underflows)
            why = (
                underflow
                if underflow is not None
                else f"all of the {on_plane:.4g} W reflected onto the plane of {target_name} lands outside the "
                f"image ({size}): the spot is off the image{hint}"
                if on_plane > 0.0
                else f"no reflected ray reaches the front of the plane of {target_name} (the heliostat is behind "
                "it, or its mirror faces away from the sun or the target)"
            )
            log.warning(
                f"no flux on the target image ({power:g} W): the centroid is undefined (null in the summary); {why}"
            )
            c = np.full(2, np.nan)
        elif underflow is not None:
            log.warning(
                f"only {power:.4g} of the {on_plane:.4g} W reflected onto the plane is on the image: {underflow}"
            )
        elif off_image is not None and off_image > OFF_IMAGE_WARNING:
            log.warning(
                f"{off_image:.1%} of the {on_plane:.4g} W reflected onto the plane of {target_name} lands outside "
                f"the image ({size}, {power:.4g} W on it): the spot is mostly off the image, and the image's "
                f"centroid and power are not the spot's{hint}"
            )
        summary = {
            "heliostat": args.heliostat,
            "target": target_name,
            "centroid_uv_m": None if not np.all(np.isfinite(c)) else c.tolist(),
            "power_w": power,
            "power_on_plane_w": on_plane,
            "off_image_fraction": off_image,
            "rays": optics.ray_count(surface, args.rays_per_point, args.steps),
            "sunshape": {
                "shape": args.sunshape,
                **({"csr": csr} if args.sunshape == "buie" else {}),
                **({"sigma_mrad": sigma_mrad} if args.sunshape == "gaussian" else {}),
                "slope_error_mrad": args.slope_error_mrad,
            },
        }
        comparison_fig = None
        flux_png = hdir / "Calibration" / f"{args.record}-flux.png"
        if args.record is not None and flux_png.exists():  # read and compared before anything is written
            log.info(f"comparing with the measured flux image {flux_png.name} (a second trace in its frame)")
            comp = optics.compare_record(
                rec_path,
                props_path,
                tower_path,
                surface=surface,
                sunshape=sunshape,
                key=jax.random.key(args.seed),
                rays_per_point=args.rays_per_point,
                steps=args.steps,
            )
            summary["comparison"] = comp.summary()
            comparison_fig = optics.comparison_figure(comp)
        elif args.record is not None:
            log.warning(f"no measured flux image {flux_png}: no comparison")
        extent = [float(grid.u_min), float(grid.u_max), float(grid.v_min), float(grid.v_max)]
        names = ("flux.h5", "flux.png", "comparison.png", "summary.json")
        outputs = [_output(args, k) if k != "comparison.png" or comparison_fig is not None else None for k in names]
        # published together: a run stopped while writing leaves the previous set as it was
        with staged_paths(outputs) as temps:
            h5_path, png_path, comparison_path, summary_path = temps
            with atomic_h5(typing.cast(Path, h5_path)) as f:
                d = f.create_dataset("flux", data=image.astype(np.float32))
                d.attrs["units"] = "W/m^2"
                d.attrs["extent_uv_m"] = extent
                d.attrs["orientation"] = "row 0 = top (max v), column 0 = left (min u)"
                f.attrs.update(
                    heliostat=args.heliostat,
                    target=target_name,
                    sun_azimuth_deg=az,
                    sun_elevation_deg=el,
                    counts=np.asarray(counts),
                    centroid_uv_m=c,
                    power_w=power,
                )
            fig, ax = plt.subplots(figsize=(5, 4.4))
            # flux is never negative: the scale starts at 0 (an image without flux is one colour, said in the title)
            top = float(image.max()) if power > 0.0 else 1.0
            im = ax.imshow(image, extent=extent, origin="upper", cmap="inferno", vmin=0.0, vmax=top)  # pyright: ignore[reportArgumentType]
            fig.colorbar(im, ax=ax, label="flux density [W/m$^2$]")
            ax.set_xlabel("u, along the target [m]")
            ax.set_ylabel("v, up the target [m]")
            none = "" if power > 0.0 else "\nno flux reached the image"
            ax.set_title(f"{args.heliostat} {tag} on {target_name}{none}", fontsize=9)
            with atomic_path(typing.cast(Path, png_path)) as tmp:
                fig.savefig(tmp, dpi=100, format="png", bbox_inches="tight")
            plt.close(fig)
            if comparison_fig is not None:
                with atomic_path(typing.cast(Path, comparison_path)) as tmp:
                    comparison_fig.savefig(tmp, dpi=90, format="png", bbox_inches="tight")
                plt.close(comparison_fig)
            summary = json_safe(summary)  # e.g. the correlation of a trace that missed the target: null
            write_json(typing.cast(Path, summary_path), summary)
        log.info(f"wrote {_output(args, 'flux')}.png, .h5 and the summary to {args.out}")
        print(json.dumps(summary, indent=2, allow_nan=False))
    except (HeliojaxError, FileNotFoundError) as e:
        print(f"heliojax trace: error: {e}", file=sys.stderr)
        return 2
    return 0
