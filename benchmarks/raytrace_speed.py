"""End-to-end ray-tracing speed: sample sun rays, reflect, intersect, splat.

    python benchmarks/raytrace_speed.py --rays 100000000 --json

Measures rays/s of :func:`heliojax.optics.flux_images` (float32, Gaussian sun,
256 x 256 image) for one heliostat (its own image) and for 100 heliostats
(padded batch, one shared target, ``combine=True``), excluding compilation,
which is timed separately.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from heliojax._geometry import TargetPlane
from heliojax.cli._common import integer
from heliojax.optics import FacetLayout, GaussianSun, ImageGrid, aim_pose, flux_images, ideal_surface, stack_surfaces


def heliostat_layout() -> FacetLayout:
    cent = np.array([[-0.8075, 0.6425], [0.8075, 0.6425], [-0.8075, -0.6425], [0.8075, -0.6425]])
    f = 65.0
    ce = np.array([[0.8025, 0, c[0] / (2 * f) * 0.8025] for c in cent])
    cn = np.array([[0, 0.6375, c[1] / (2 * f) * 0.6375] for c in cent])
    return FacetLayout.from_arrays(np.c_[cent, np.full(4, 0.04)], ce, cn)


def scene(n_heliostats: int, resolution: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    target = TargetPlane.from_corners([3.0, 0, 126.5], [-3.0, 0, 126.5], [3.0, 0, 119.3], [-3.0, 0, 119.3])
    sun = jnp.asarray([0.3, -0.6, 0.74]) / np.linalg.norm([0.3, -0.6, 0.74])
    surf = ideal_surface(heliostat_layout(), (resolution, resolution))
    positions = np.c_[
        rng.uniform(-100, 100, n_heliostats), rng.uniform(50, 250, n_heliostats), np.full(n_heliostats, 1.5)
    ]
    poses = [aim_pose(jnp.asarray(p), sun, target.centre) for p in positions]
    poses = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *poses)
    surfs = stack_surfaces([surf] * n_heliostats)
    return surfs, poses, sun, target, ImageGrid.for_target(target, (256, 256))


def run_case(n_heliostats: int, rays: int, resolution: int, chunk: int, repeats: int) -> dict:
    surfs, poses, sun, target, grid = scene(n_heliostats, resolution)
    points = n_heliostats * surfs.points.shape[1]
    rays_per_point = max(1, min(chunk // points, rays // points))
    steps = max(1, rays // (points * rays_per_point))
    total = points * rays_per_point * steps
    combine = n_heliostats > 1
    fn = jax.jit(
        lambda k: flux_images(
            k,
            surfs,
            poses,
            sun,
            target,
            grid,
            GaussianSun(2.51e-3),
            rays_per_point=rays_per_point,
            steps=steps,
            combine=combine,
        )
    )
    t0 = time.perf_counter()
    compiled = fn.lower(jax.random.key(0)).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(jax.random.key(0)))  # warm-up
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(jax.random.key(r + 1)))
        times.append(time.perf_counter() - t0)
    best = min(times)
    return {
        "heliostats": n_heliostats,
        "points": points,
        "rays": total,
        "rays_per_point_per_step": rays_per_point,
        "steps": steps,
        "compile_s": round(compile_s, 3),
        "run_s_best": round(best, 4),
        "run_s_median": round(float(np.median(times)), 4),
        "mrays_per_s": round(total / best / 1e6, 2),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rays", type=integer(1), default=20_000_000, help="rays per case (default 2e7)")
    p.add_argument("--resolution", type=integer(1), default=16, help="surface points per facet edge (default 16)")
    p.add_argument("--chunk", type=integer(1), default=1 << 21, help="rays per lax.scan step (default 2^21)")
    p.add_argument("--repeats", type=integer(1), default=3)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    cases = [run_case(n, args.rays, args.resolution, args.chunk, args.repeats) for n in (1, 100)]
    out = {
        "benchmark": "raytrace_speed",
        "backend": jax.default_backend(),
        "device": str(jax.devices()[0]),
        "cpu_count": __import__("os").cpu_count(),
        "machine": platform.machine(),
        "dtype": "float32",
        "cases": cases,
    }
    if args.json:
        print(json.dumps(out))
    else:
        for c in cases:
            print(
                f"{c['heliostats']:4d} heliostats: {c['rays']:.3g} rays in {c['run_s_best']:.3f} s = "
                f"{c['mrays_per_s']:.1f} Mrays/s (compile {c['compile_s']:.1f} s)"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
