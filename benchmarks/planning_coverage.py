"""Does the predicted pointing uncertainty hold? Aim and plan coverage on the
independent simulator (``independent_sim/``, shares no code with heliojax).

Protocol (issue 15, acceptance items 1 and 4):

1. ``independent_sim`` writes a null suite (no hidden effect, real Jülich
   heliostats and record times, drawn plant errors, 0.25 mrad camera noise).
2. heliojax calibrates every heliostat on all its records (robust, pooled); the
   fleet prior for heliostat ``i`` is learnt from the *other* heliostats' fits.
3. For K = 4, 8, 16 the planner chooses K of the heliostat's records (start: the
   leave-one-out prior; envelope: a year of DNI-weighted suns aiming at the
   receiver), and heliojax fits those K records under the same prior.
4. ``heliojax.aim_fleet`` commands every heliostat at the receiver at 40 random
   daylight instants of a year, with the predicted 2x2 pointing covariance from
   (a) the fit's posterior covariance and (b) the plan's predicted covariance.
5. The *true* beam of the commanded counts comes from ``independent_sim``'s
   own kinematics (``plant_mount``): its angle to the receiver, as the two
   tangent-plane components, against the predicted covariance: the fraction of
   commands with Mahalanobis d^2 inside the 68 % and 95 % chi^2_2 quantiles
   (target 60-76 % and 90-98 %).

    python benchmarks/planning_coverage.py --seeds 1 2
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import heliojax as hj  # noqa: E402
from heliojax.cli._common import integer  # noqa: E402
from heliojax.fitting import GaussianPrior, prior_moments, well_determined  # noqa: E402
from heliojax.optics import target_from_tower  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import independent_sim  # noqa: E402

CHI2_2 = {"68": 2.2788, "95": 5.9915}
BUDGETS = (4, 8, 16)
LAT, LON = 50.913421122592574, 6.387824755874856


def true_components(mount, counts: np.ndarray, sun: np.ndarray, aim: np.ndarray) -> np.ndarray:
    """``(N, 2)`` beam error components (mrad) of the *true* plant at ``counts`` (N, 2): the
    direction to ``aim`` in the tangent basis of the true reflected ray (e1 = up x r, e2 = r x e1)."""
    t1, t2 = mount.act1.angle(counts[:, 0]), mount.act2.angle(counts[:, 1])
    normal, centre = mount.pose(t1, t2)
    r = independent_sim.reflect(sun, normal)
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    d = aim[None, :] - centre
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    e1 = np.cross(np.array([0.0, 0.0, 1.0]), r)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(r, e1)
    return 1e3 * np.stack([np.sum(d * e1, -1), np.sum(d * e2, -1)], -1)


def coverage(v: np.ndarray, cov: np.ndarray) -> dict:
    ok = np.all(np.isfinite(v), axis=-1) & np.all(np.isfinite(cov), axis=(-2, -1))
    d2 = np.einsum("ni,nij,nj->n", v[ok], np.linalg.inv(cov[ok]), v[ok])
    return {
        "commands": int(ok.sum()),
        **{f"coverage_{q}": float(np.mean(d2 < x)) for q, x in CHI2_2.items()},
        "median_d2": float(np.median(d2)),
        "rms_error_mrad": float(np.sqrt(np.mean(np.sum(v[ok] ** 2, -1)))),
        "rms_predicted_mrad": float(np.sqrt(np.mean(np.trace(cov[ok], axis1=-2, axis2=-1)))),
    }


def one_seed(seed: int, workdir: Path, heliostats: int, records: int) -> dict:
    suite = workdir / f"null-{seed}"
    independent_sim.generate("none", suite, seed=seed, n_heliostats=heliostats, n_records=records)
    fleet = hj.load_paint_directory(suite)
    ids = list(fleet.ids)
    h = len(ids)
    everything = {hid: {int(r): "train" for r in np.asarray(fleet.record_id)[i][np.asarray(fleet.mask)[i]]}
                  for i, hid in enumerate(ids)}  # fmt: skip
    run = hj.calibrate(fleet, model="actuator", record_roles=everything, changes=False)
    sol, padded = run.result, run.fleet
    view = sol.view
    params, std = np.asarray(sol.parameters())[:h], np.asarray(sol.std)[:h]
    good = np.asarray(well_determined(sol))[:h]
    model0 = hj.nominal_model("actuator")
    nominal = np.asarray(view.to_vector(model0), float)
    noise = float(np.median(np.asarray(run.noise_mrad)[:h][good]))
    moments = [prior_moments(view, params, std, good & (np.arange(h) != i), nominal) for i in range(h)]
    centres = np.stack([c for c, _ in moments])
    spreads = np.stack([s for _, s in moments])
    free, scales = np.asarray(view.free_index), np.asarray(view.scales)
    cov0 = np.stack([np.diag(np.where(np.isfinite(s[free]), s[free], 10.0 * scales[free]) ** 2) for s in spreads])
    base = hj.broadcast_model(model0, h)
    centre_models = jax.vmap(view.from_vector)(base, jnp.asarray(centres))
    sigma_models = jax.vmap(view.from_vector)(base, jnp.asarray(spreads))

    take = lambda x: jnp.asarray(x)[:h]  # noqa: E731
    geometry = jax.tree.map(take, padded.geometry)
    counts, context, spots = take(padded.counts), jax.tree.map(take, padded.context), take(padded.focal_spot)
    candidates = take(padded.mask)
    tower = hj.read_tower(next(suite.glob("*-tower-measurements.json")))
    receiver = np.asarray(target_from_tower(tower, "receiver").centre)
    sun_e, w_e = hj.operating_envelope(np.asarray(fleet.origin_lla))
    jac = hj.residual_jacobians(centre_models, view, geometry, counts, context, spots, candidates)
    m_env = hj.envelope_matrices(centre_models, view, geometry, sun_e, w_e, jnp.asarray(receiver))
    plan = hj.plan_measurements(jnp.asarray(cov0), jac, candidates, m_env, noise, max(BUDGETS))
    chosen = np.asarray(plan.chosen)

    rng = np.random.default_rng(seed)
    unix = hj.datetime_to_unix("2024-01-01T00:00:00Z") + rng.uniform(0, 366 * 86400.0, 400)
    position = hj.solar_position(jnp.asarray(unix), *np.asarray(fleet.origin_lla))
    up = np.asarray(position.elevation) > np.radians(15.0)
    sun = np.asarray(position.direction_enu())[up][:40]
    mounts = [independent_sim.plant_mount(suite, hid) for hid in ids]
    prior = GaussianPrior(centre=centre_models, sigma=sigma_models, noise_mrad=jnp.full((h,), noise))
    out: dict = {"seed": seed, "heliostats": h, "noise_mrad": noise, "instants": int(sun.shape[0])}
    for k in BUDGETS:
        mask = np.zeros(np.shape(candidates), bool)
        for i in range(h):
            mask[i, chosen[i][:k][chosen[i][:k] >= 0]] = True
        fitted = hj.fit(centre_models, _subset(padded, h), mask=jnp.asarray(mask), prior=prior)
        # the plan's covariance after its first k choices: the greedy run for budget k
        plan_k = hj.plan_measurements(jnp.asarray(cov0), jac, candidates, m_env, noise, k)
        result = {}
        for name, cov in (("fit_posterior", fitted.covariance), ("plan_predicted", plan_k.covariance_after)):
            aim = hj.aim_fleet(
                fitted.model, geometry, jnp.asarray(sun), jnp.asarray(receiver), covariance=cov, view=view
            )
            c = np.asarray(aim.counts)
            pred = np.asarray(aim.pointing_cov_mrad2)
            real = np.stack([true_components(mounts[i], c[i], sun, receiver) for i in range(h)])
            use = np.asarray(aim.ok)
            result[name] = coverage(real[use], pred[use])
        out[f"K={k}"] = result
    return out


def _subset(padded, h: int):
    """The first ``h`` heliostats of a padded fleet, as the arrays :func:`heliojax.fit` reads."""
    import types

    take = lambda x: jnp.asarray(x)[:h]  # noqa: E731
    return types.SimpleNamespace(
        geometry=jax.tree.map(take, padded.geometry),
        counts=take(padded.counts),
        context=jax.tree.map(take, padded.context),
        focal_spot=take(padded.focal_spot),
        mask=take(padded.mask),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=integer(0), nargs="+", default=[1])
    ap.add_argument("--heliostats", type=integer(1), default=20)
    ap.add_argument("--records", type=integer(1), default=60)
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        runs = [one_seed(s, Path(tmp), args.heliostats, args.records) for s in args.seeds]
    print(json.dumps({"benchmark": "planning_coverage", "runs": runs, "wall_s": round(time.perf_counter() - t0, 1)},
                     indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
