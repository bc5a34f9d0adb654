"""Aiming speed: counts for H heliostats x N instants with calibrated models
(issue target: 10,000 x 48 in under 2 s on a 2-core CPU after compilation).

Prints JSON: compile (first call) and warm wall time, and the worst forward-model
miss of the commanded counts on the instants that raise no flag.

    python benchmarks/aim_speed.py --heliostats 10000 --instants 48
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import heliojax as hj  # noqa: E402
from heliojax.cli._common import integer  # noqa: E402
from heliojax.discovery import simulate_fleet  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--heliostats", type=integer(1), default=10_000)
    ap.add_argument("--instants", type=integer(1), default=48)
    ap.add_argument("--repeats", type=integer(1), default=3)
    args = ap.parse_args()
    base_h = 50
    fleet, truth = simulate_fleet(0, base_h, 8, base="actuator", noise_mrad=0.0)
    reps = -(-args.heliostats // base_h)
    tile = lambda x: jnp.concatenate([x] * reps, 0)[: args.heliostats]  # noqa: E731
    geometry = jax.tree.map(tile, fleet.geometry)
    models = jax.tree.map(tile, truth)
    day = 1660348800.0 + np.linspace(6, 18, args.instants) * 3600.0  # 2022-08-13, 06-18 UTC
    sun = hj.solar_position(day, 50.913421122592574, 6.387824755874856, 87.0).direction_enu()
    aim = jnp.array([0.0, 0.0, 60.0])
    t0 = time.perf_counter()
    r = hj.aim_fleet(models, geometry, sun, aim)
    jax.block_until_ready(r.counts)
    first = time.perf_counter() - t0
    warm = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        r = hj.aim_fleet(models, geometry, sun, aim)
        jax.block_until_ready(r.counts)
        warm.append(time.perf_counter() - t0)
    ok = np.asarray(r.ok)
    print(
        json.dumps(
            {
                "heliostats": args.heliostats,
                "instants": args.instants,
                "first_call_s": first,
                "warm_s": min(warm),
                "warm_all_s": warm,
                "ok_fraction": float(ok.mean()),
                "max_model_miss_ok_mrad": float(np.asarray(r.model_miss_mrad)[ok].max()) if ok.any() else None,
                "backend": jax.default_backend(),
                "machine": platform.processor() or platform.machine(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
