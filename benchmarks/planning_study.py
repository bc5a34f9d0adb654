"""Retrospective planning study on real records: does the planner choose better
calibration records than time order or chance?

Protocol (issue 15, fixed before looking at any result):

* every heliostat with at least ``--min-records`` (40) timed records takes part;
  its records before its own 70 % time quantile are the candidate pool, the
  later ones the test set;
* the fleet prior is learnt from a robust, pooled fit of every heliostat's pool
  (``heliojax.calibrate`` defaults: actuator model, start geometry chosen on the
  pool), *leaving out the heliostat itself* (what the fleet knows before this
  heliostat has a record); pool records that this fit's change-point scan puts
  before a change (a past state) are no candidates for any of the selections;
* for K = 4, 6, 8, 12, 16 these selections of K pool records are compared:
  the planner's (greedy I-optimal, :func:`heliojax.plan_measurements`, from the
  leave-one-out prior, linearised at its centre, operating envelope: a year of
  sun positions weighted by clear-sky DNI aiming at the receiver), the same
  planner for a model that is not exact (:func:`heliojax.discrepancy_design`,
  the discrepancy learnt from the pool fit's training inliers; added 2026-11-26),
  each of the two with every candidate's noise aged by the fleet's drift
  (:func:`heliojax.aged_noise_mrad`; added 2026-12-05) and with a random day effect
  (records of one day share an error: ``plan_measurements(day=, day_correlation=)``
  with the pool fit's intra-day correlation, :func:`heliojax.fitting.day_clustering`;
  added 2026-12-07), the first K in time, and K at random (20 draws);
* each selection is fitted by least squares under the same leave-one-out prior,
  all lanes in one compiled program, and judged by the median beam error on the
  heliostat's test records.

Prints JSON: per K the median over heliostats of the held-out median (planner,
first K, random: median over draws), how often the planner is at least as good
as random (the median of its draws), per heliostat the share of random draws that
beat the planner (``*_beaten_by_random_share``: 0.5 is as good as random), and
the issue's goal (planner with K at or below first-in-time with 2K). ``--figure
PATH`` draws the table.

    python benchmarks/planning_study.py ../shared/data/paint --figure docs/figures/planning_study.png
"""

from __future__ import annotations

import argparse
import json
import time
import types
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import heliojax as hj  # noqa: E402
from heliojax._errors import ConfigError  # noqa: E402
from heliojax._plotting import save_figure  # noqa: E402
from heliojax.cli._common import check_output_paths, integer, number  # noqa: E402
from heliojax.fitting import (  # noqa: E402  # noqa: E402
    GaussianPrior,
    day_clustering,
    day_labels,
    fleet_beam_errors_mrad,
    prior_moments,
    well_determined,
)
from heliojax.optics import target_from_tower  # noqa: E402

BUDGETS = (4, 6, 8, 12, 16)
PLANNERS = (
    "planner",
    "planner_discrepancy",
    "planner_drift",
    "planner_discrepancy_drift",
    "planner_days",
    "planner_discrepancy_days",
)
"""The planners compared: exact model or with a model discrepancy, each with every
candidate at the fit's noise, with the noise grown by its age under the fleet's
pointing drift (:func:`heliojax.aged_noise_mrad`; added 2026-12-05), or with a random
day effect (added 2026-12-07)."""


def lane_fleet(padded, rows: np.ndarray, mask: np.ndarray):
    """The arrays :func:`heliojax.fit` reads, one lane per entry of ``rows``."""
    take = lambda x: jnp.asarray(x)[jnp.asarray(rows)]  # noqa: E731
    return types.SimpleNamespace(
        geometry=jax.tree.map(take, padded.geometry),
        counts=take(padded.counts),
        context=jax.tree.map(take, padded.context),
        focal_spot=take(padded.focal_spot),
        mask=jnp.asarray(mask),
    )


def padded_times(padded, h: int, m_pad: int) -> np.ndarray:
    """``(h, m_pad)`` record times (s) of the padded fleet."""
    return np.asarray(padded.context.unix_time, float)[:h, :m_pad]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", type=Path, help="PAINT directory (e.g. ../shared/data/paint)")
    ap.add_argument("--min-records", type=integer(1), default=40)
    ap.add_argument("--pool-quantile", type=number(0.0, 1.0), default=0.7)
    ap.add_argument("--draws", type=integer(1), default=20)
    ap.add_argument("--seed", type=integer(0), default=0)
    ap.add_argument("--figure", type=Path, default=None)
    args = ap.parse_args()
    try:  # before the work: a folder or an unwritable place named as the output had failed after it
        check_output_paths(args, ("figure",))
    except ConfigError as e:
        ap.error(str(e))
    out = study(args.data_dir, args.min_records, args.pool_quantile, args.draws, args.seed)
    print(json.dumps(out, indent=2))
    if args.figure is not None:
        plot(out, args.figure)


def study(
    data_dir: Path,
    min_records: int = 40,
    pool_quantile: float = 0.7,
    draws: int = 20,
    seed: int = 0,
    keep_lanes: bool = False,
) -> dict:
    """The study on one PAINT directory (module docstring); returns the JSON object
    (with ``keep_lanes``, also ``"_lanes"``: each lane's key ``(heliostat, K, method,
    draw)``, fitted model and geometry, for judging the selections otherwise)."""
    args = types.SimpleNamespace(
        data_dir=Path(data_dir), min_records=min_records, pool_quantile=pool_quantile, draws=draws, seed=seed
    )
    t_start = time.perf_counter()

    fleet = hj.load_paint_directory(args.data_dir)
    ids = list(fleet.ids)
    h = len(ids)
    valid = np.asarray(fleet.mask) & np.isfinite(np.asarray(fleet.context.unix_time))
    times = np.where(valid, np.asarray(fleet.context.unix_time), np.nan)
    cut = np.array(
        [np.quantile(times[i][valid[i]], args.pool_quantile) if valid[i].any() else np.nan for i in range(h)]
    )
    pool = valid & (times < cut[:, None])
    test = valid & (times >= cut[:, None])
    record_id = np.asarray(fleet.record_id)
    roles = {
        hid: {int(r): "train" for r in record_id[i][pool[i]]} | {int(r): "test" for r in record_id[i][test[i]]}
        for i, hid in enumerate(ids)
    }
    run = hj.calibrate(fleet, model="actuator", record_roles=roles)
    sol, padded = run.result, run.fleet
    view = sol.view
    params = np.asarray(sol.parameters())[:h]
    std = np.asarray(sol.std)[:h]
    good = np.asarray(well_determined(sol))[:h]
    model0 = hj.nominal_model("actuator")
    nominal = np.asarray(view.to_vector(model0), float)
    noise = float(np.median(np.asarray(run.noise_mrad)[:h][good]))
    study = [i for i in range(h) if valid[i].sum() >= args.min_records]
    s = len(study)
    free = np.asarray(view.free_index)
    scales = np.asarray(view.scales)

    centres, spreads = [], []
    for i in study:
        others = good & (np.arange(h) != i)
        c, sp = prior_moments(view, params, std, others, nominal)
        centres.append(c)
        spreads.append(sp)
    centres, spreads = np.stack(centres), np.stack(spreads)
    base = hj.broadcast_model(model0, s)
    centre_models = jax.vmap(view.from_vector)(base, jnp.asarray(centres))
    sd = spreads[:, free]
    cov0 = np.stack([np.diag(np.where(np.isfinite(x), x, 10.0 * scales[free]) ** 2) for x in sd])

    # The plan: candidates are the pool records, linearised at the leave-one-out prior's centre.
    rows = np.asarray(study)
    m_pad = padded.mask.shape[1]

    def pad(mk):
        out = np.zeros((mk.shape[0], m_pad), bool)
        out[:, : mk.shape[1]] = mk
        return out

    pool_p, test_p = pad(pool), pad(test)
    # Records before a change point the pool's fit found describe a past state: no candidates.
    superseded = np.asarray(run.superseded)[: pool_p.shape[0], :m_pad]
    n_superseded = int((pool_p & superseded).sum())
    pool_p &= ~superseded
    sub = lane_fleet(padded, rows, pool_p[rows])
    tower_file = next(args.data_dir.glob("*-tower-measurements.json"))
    receiver = np.asarray(target_from_tower(hj.read_tower(tower_file), "receiver").centre)
    sun_e, w_e = hj.operating_envelope(np.asarray(fleet.origin_lla))
    jac = hj.residual_jacobians(
        centre_models, view, sub.geometry, sub.counts, sub.context, sub.focal_spot, jnp.asarray(pool_p[rows])
    )
    m_env = hj.envelope_matrices(centre_models, view, sub.geometry, sun_e, w_e, jnp.asarray(receiver))
    # Drift: the pointing random walk the pool's fit learnt (time-blocked validation on
    # the pool records); each candidate's noise grows with its age at the cut.
    drift_q = float(run.predictive.get("drift_mrad2_per_day", 0.0))
    aged = hj.aged_noise_mrad(noise, drift_q, np.asarray(sub.context.unix_time), pool_p[rows])
    plan = hj.plan_measurements(jnp.asarray(cov0), jac, jnp.asarray(pool_p[rows]), m_env, noise, max(BUDGETS))
    chosen = np.asarray(plan.chosen)
    plan_a = hj.plan_measurements(jnp.asarray(cov0), jac, jnp.asarray(pool_p[rows]), m_env, aged, max(BUDGETS))
    chosen_a = np.asarray(plan_a.chosen)

    # The same plan for a model that is not exact: the discrepancy process learnt from the
    # pool fit's residuals (training inliers of well-determined heliostats; no test record).
    normals = np.asarray(hj.mirror_normals(padded.geometry.position, padded.context.sun, padded.focal_spot))[:h, :m_pad]
    outlier = np.asarray(run.outlier if run.outlier is not None else np.zeros(pool_p.shape, bool))[:h, :m_pad]
    learn = pool_p & ~outlier & ~superseded & good[:, None]
    discrepancy = hj.estimate_discrepancy(np.asarray(run.residuals_mrad)[:h, :m_pad], normals, learn)
    cands = hj.Candidates(
        counts=sub.counts,
        context=sub.context,
        spots=sub.focal_spot,
        valid=jnp.asarray(pool_p[rows]),
        slot=jnp.broadcast_to(jnp.arange(m_pad, dtype=jnp.int32), (s, m_pad)),
    )
    design = hj.discrepancy_design(discrepancy, sub.geometry, jnp.asarray(cov0), jac, cands, sun_e, receiver)
    m_env_d = hj.envelope_matrices(
        centre_models,
        view,
        sub.geometry,
        sun_e,
        w_e,
        jnp.asarray(receiver),
        discrepancy=discrepancy,
        inducing=design.inducing,
    )
    plan_d = hj.plan_measurements(
        design.covariance, design.candidate_jacobians, cands.valid, m_env_d, noise, max(BUDGETS)
    )
    chosen_d = np.asarray(plan_d.chosen)
    plan_da = hj.plan_measurements(
        design.covariance, design.candidate_jacobians, cands.valid, m_env_d, aged, max(BUDGETS)
    )
    chosen_da = np.asarray(plan_da.chosen)

    # Records of one day share an error: the intra-day correlation of the pool fit's
    # training inliers (well-determined heliostats), each candidate labelled by its day.
    clustering = day_clustering(
        np.asarray(run.residuals_mrad)[:h, :m_pad],
        learn,
        np.where(pool_p, padded_times(padded, h, m_pad), np.nan),
        len(free),
    )
    rho = clustering.correlation
    days = day_labels(np.asarray(sub.context.unix_time))
    plan_y = hj.plan_measurements(
        jnp.asarray(cov0), jac, jnp.asarray(pool_p[rows]), m_env, noise, max(BUDGETS), day=days, day_correlation=rho
    )
    chosen_y = np.asarray(plan_y.chosen)
    plan_dy = hj.plan_measurements(
        design.covariance,
        design.candidate_jacobians,
        cands.valid,
        m_env_d,
        noise,
        max(BUDGETS),
        day=days,
        day_correlation=rho,
    )
    chosen_dy = np.asarray(plan_dy.chosen)

    # Selections -> lanes.
    rng = np.random.default_rng(args.seed)
    lanes_row, lanes_prior, lanes_mask, lanes_key = [], [], [], []
    for si, i in enumerate(study):
        cand = np.flatnonzero(pool_p[i])
        by_time = cand[np.argsort(times[i][cand])]
        for k in BUDGETS:
            picks = {
                "planner": [chosen[si][:k][chosen[si][:k] >= 0]],
                "planner_discrepancy": [chosen_d[si][:k][chosen_d[si][:k] >= 0]],
                "planner_drift": [chosen_a[si][:k][chosen_a[si][:k] >= 0]],
                "planner_discrepancy_drift": [chosen_da[si][:k][chosen_da[si][:k] >= 0]],
                "planner_days": [chosen_y[si][:k][chosen_y[si][:k] >= 0]],
                "planner_discrepancy_days": [chosen_dy[si][:k][chosen_dy[si][:k] >= 0]],
                "first": [by_time[:k]],
            }
            picks["random"] = [rng.choice(cand, size=min(k, cand.size), replace=False) for _ in range(args.draws)]
            for method, sets in picks.items():
                for d, sel in enumerate(sets):
                    mk = np.zeros(m_pad, bool)
                    mk[sel] = True
                    lanes_row.append(i)
                    lanes_prior.append(si)
                    lanes_mask.append(mk)
                    lanes_key.append((ids[i], k, method, d))
    lanes_row, lanes_prior = np.asarray(lanes_row), np.asarray(lanes_prior)
    n_lanes = len(lanes_key)
    lanes = lane_fleet(padded, lanes_row, np.asarray(lanes_mask))
    n_pad = hj.bucket_size(n_lanes)
    fill = np.concatenate([np.arange(n_lanes), np.zeros(n_pad - n_lanes, int)])
    lanes = lane_fleet(
        padded, lanes_row[fill], np.concatenate([np.asarray(lanes_mask), np.zeros((n_pad - n_lanes, m_pad), bool)])
    )
    centre_l = jax.vmap(view.from_vector)(hj.broadcast_model(model0, n_pad), jnp.asarray(centres[lanes_prior[fill]]))
    sigma_l = jax.vmap(view.from_vector)(hj.broadcast_model(model0, n_pad), jnp.asarray(spreads[lanes_prior[fill]]))
    prior = GaussianPrior(centre=centre_l, sigma=sigma_l, noise_mrad=jnp.full((n_pad,), noise))
    t0 = time.perf_counter()
    fitted = hj.fit(centre_l, lanes, prior=prior)
    fit_s = time.perf_counter() - t0
    test_lanes = lane_fleet(padded, lanes_row[fill], test_p[lanes_row[fill]])
    err = np.asarray(fleet_beam_errors_mrad(fitted.model, test_lanes))[:n_lanes]
    lane_median = np.nanmedian(err, axis=1)

    full_err = np.asarray(run.errors_mrad)[:h]
    table: dict[str, dict] = {}
    per_heliostat: dict[str, dict] = {}
    for k in BUDGETS:
        rowk: dict[str, list[float]] = {m: [] for m in (*PLANNERS, "first", "random")}
        share: dict[str, list[float]] = {m: [] for m in PLANNERS}
        for i in study:
            got = {m: [v for v, key in zip(lane_median, lanes_key, strict=True) if key[:3] == (ids[i], k, m)]
                   for m in rowk}  # fmt: skip
            vals = {m: float(np.median(v)) for m, v in got.items()}
            for m in rowk:
                rowk[m].append(vals[m])
            draws_i = np.asarray(got["random"])
            for m in share:  # the share of random draws that beat this selection
                share[m].append(float(np.mean(draws_i < vals[m])))
            per_heliostat.setdefault(ids[i], {})[str(k)] = {m: round(v, 3) for m, v in vals.items()} | {
                f"{m}_beaten_by_random_share": round(share[m][-1], 2) for m in share
            }
        arr = {m: np.asarray(v) for m, v in rowk.items()}
        table[str(k)] = {
            **{f"{m}_mrad": float(np.median(arr[m])) for m in PLANNERS},
            "first_in_time_mrad": float(np.median(arr["first"])),
            "random_mrad": float(np.median(arr["random"])),
            **{f"{m}_not_worse_than_random": f"{int(np.sum(arr[m] <= arr['random']))}/{s}" for m in PLANNERS},
            "planner_not_worse_than_first": f"{int(np.sum(arr['planner'] <= arr['first']))}/{s}",
            # per heliostat, the share of the random draws that beat the selection:
            # 0.5 is as good as random, above 0.75 clearly worse
            **{
                f"{m}_beaten_by_random_share": {
                    "median": float(np.median(v)),
                    "max": float(np.max(v)),
                    "heliostats_above_0.75": f"{int(np.sum(np.asarray(v) > 0.75))}/{s}",
                }
                for m, v in share.items()
            },
        }
    goal = {}
    for k in BUDGETS:
        if str(2 * k) in table:
            for name in PLANNERS:
                goal[f"{name}_{k}_vs_first_{2 * k}"] = {
                    f"{name}_mrad": table[str(k)][f"{name}_mrad"],
                    "first_in_time_mrad": table[str(2 * k)]["first_in_time_mrad"],
                    "met": table[str(k)][f"{name}_mrad"] <= table[str(2 * k)]["first_in_time_mrad"],
                }
    full = [float(np.nanmedian(np.where(test[i], full_err[i, : test.shape[1]], np.nan))) for i in study]
    out = {
        "benchmark": "planning_study",
        "data": str(args.data_dir),
        "heliostats": [ids[i] for i in study],
        "pool_records_median": int(np.median(pool[study].sum(axis=1))),
        "test_records_median": int(np.median(test[study].sum(axis=1))),
        "noise_mrad": noise,
        "drift_mrad2_per_day": drift_q,
        "discrepancy": {
            "amplitude_mrad": float(discrepancy.amplitude_mrad),
            "length": float(discrepancy.length),
            "nugget_mrad": float(discrepancy.nugget_mrad),
        },
        "intra_day_correlation": clustering.as_dict(),
        "pool_records_superseded_by_change_points": n_superseded,
        "lanes": n_lanes,
        "fit_s": round(fit_s, 2),
        "table": table,
        "goal_K_vs_first_2K": goal,
        "whole_pool_robust_pooled_mrad": float(np.median(full)),
        "per_heliostat": per_heliostat,
        "wall_s": round(time.perf_counter() - t_start, 1),
    }
    if keep_lanes:
        out["_lanes"] = {"keys": lanes_key, "model": fitted.model, "geometry": lanes.geometry}
    return out


def plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = np.asarray(BUDGETS)
    fig, ax = plt.subplots(figsize=(10.0, 4.8))
    styles = {"planner_mrad": ("planner (I-optimal, exact model)", "o-", "tab:blue"),
              "planner_discrepancy_mrad": ("planner with model discrepancy", "D-", "tab:purple"),
              "planner_drift_mrad": ("planner, noise aged by the drift", "o-.", "tab:cyan"),
              "planner_discrepancy_drift_mrad": ("planner with discrepancy, noise aged", "D-.", "tab:pink"),
              "planner_days_mrad": ("planner, day effect", "o--", "tab:red"),
              "planner_discrepancy_days_mrad": ("planner with discrepancy, day effect", "D--", "tab:brown"),
              "first_in_time_mrad": ("first K in time", "s--", "tab:orange"),
              "random_mrad": ("K at random (median of draws)", "^:", "tab:green")}  # fmt: skip
    for key, (label, style, colour) in styles.items():
        ax.plot(ks, [out["table"][str(k)][key] for k in ks], style, color=colour, label=label)
    ax.axhline(out["whole_pool_robust_pooled_mrad"], color="0.4", lw=1, label="whole pool (robust, pooled)")
    ax.set_xlabel("calibration records per heliostat, K")
    ax.set_ylabel("held-out median beam error [mrad]\n(median over heliostats)")
    ax.set_xticks(ks)
    ax.set_title(f"Retrospective planning study, {len(out['heliostats'])} real heliostats (PAINT)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)  # atomically: an interrupted run leaves no half-written PNG


if __name__ == "__main__":
    main()
