"""How well the robust fit predicts under noise laws it was not written for.

    python benchmarks/robust_efficiency.py [--heliostats 200] [--records 60] [--seeds 1 2 3]

Simulated Stone fleets (:func:`calibration_speed.simulate_fleet`, noise-free
records); the earliest 70 % of each heliostat's records train, with noise added to
their focal spots: two tangent-plane components of ``--scale`` mrad times a draw of
the law (Gaussian, Student t with 10, 5, 3 and 2 degrees of freedom, and Gaussian
with 5 % of the records displaced by 10-100 mrad). The held-out records stay
noise-free, so their RMS beam error is the fitted model's error against the truth.
Per law: that RMS for least squares (:func:`heliojax.fit`) and for the robust fit
(:func:`heliojax.fitting.fit_robust`, no pooling), and how many heliostats the robust
fit sent through its Cauchy passes. Prints JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from heliojax.cli._common import integer, number

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import calibration_speed as cs  # noqa: E402

LAWS = ("gaussian", "t10", "t5", "t3", "t2", "gaussian+gross5%")


def tangent_noise(focal, position, law, scale_mrad, rng):
    """``focal`` ``(N, M, 3)`` with each spot moved by a beam error of two independent
    components of ``scale_mrad`` times a draw of ``law``, perpendicular to the
    heliostat-to-spot direction."""
    d = focal - position[:, None, :]
    dist = np.linalg.norm(d, axis=-1, keepdims=True)
    u = np.cross(d / dist, np.array([0.0, 0.0, 1.0]))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    v = np.cross(d / dist, u)
    shape = focal.shape[:2] + (2,)
    if law.startswith("gaussian"):
        z = rng.normal(size=shape)
    else:
        z = rng.standard_t(int(law[1:]), size=shape)
    z = z * scale_mrad * 1e-3
    return focal + dist * (z[..., :1] * u + z[..., 1:] * v)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--heliostats", type=integer(1), default=200)
    p.add_argument("--records", type=integer(1), default=60)
    p.add_argument("--scale", type=number(0.0, above=True), default=0.2, help="noise scale per component (mrad)")
    p.add_argument("--seeds", type=integer(0), nargs="+", default=[1, 2, 3])
    args = p.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    import heliojax as hj

    n, m = args.heliostats, args.records
    n_train = int(round(0.7 * m))
    model = hj.StoneModel.nominal(jnp.float64)
    out: dict = {"heliostats": n, "records": m, "train_records": n_train, "scale_mrad": args.scale, "laws": {}}
    t0 = time.perf_counter()
    for seed in args.seeds:
        geometry, true, context, counts, focal, _ = cs.simulate_fleet(n, m, 0.0, seed=seed)
        tr, te = np.arange(n_train), np.arange(n_train, m)
        test = [cs._take_records(x, te) for x in (context, counts, focal)]
        test_mask = np.ones((n, m - n_train), bool)
        for k, law in enumerate(LAWS):
            rng = np.random.default_rng(1000 * seed + k)
            train = [cs._take_records(x, tr) for x in (context, counts, focal)]
            train[2] = tangent_noise(np.asarray(train[2]), np.asarray(geometry.position), law, args.scale, rng)
            if law.endswith("gross5%"):
                train[2], _ = cs.plant_gross_errors(train[2], np.asarray(geometry.position), 0.05, seed)
            data = cs.heliojax_data(geometry, *train, np.ones((n, n_train), bool), pad=True)
            ls = hj.fit(model, data)
            rob = hj.fitting.fit_robust(model, data)
            row = {}
            for name, sol in (("least_squares", ls), ("robust", rob.solution)):
                params = np.asarray(sol.parameters())[:n, :8]
                row[name] = cs.heldout_rms(params, geometry, *test, test_mask)[0]
            row["cauchy_heliostats"] = int(np.isfinite(np.asarray(rob.scale_mrad))[:n].sum())
            agg = out["laws"].setdefault(law, {"least_squares": [], "robust": [], "cauchy_heliostats": []})
            for key, val in row.items():
                agg[key].append(val)
            print(f"seed {seed} {law}: {row}", file=sys.stderr)
    for agg in out["laws"].values():
        agg["least_squares_mean"] = float(np.mean(agg["least_squares"]))
        agg["robust_mean"] = float(np.mean(agg["robust"]))
    out["wall_s"] = time.perf_counter() - t0
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
