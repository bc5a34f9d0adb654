"""Coverage of the predicted pointing uncertainty on real held-out records.

Calibrates a PAINT directory (default model, time split, robust, pooled), then for
every held-out record of a converged heliostat compares its residual (mrad, two
tangent components) with the predicted covariance ``J C J^T`` (the parameter
covariance propagated through the residual's Jacobian, as ``heliojax aim`` does)
plus the fit's noise per component, plus the fleet's drift since each heliostat's
last fitted record, its rate estimated from the training records alone
(:func:`heliojax.temporal_drift`), plus the sky-gap term (the growth per degree from
the record's sun to the nearest fitted record's sun, where the same training
records ask for it), the scale of the error law (:class:`heliojax.PointingErrorLaw`,
a Student t or a Gaussian, with or without an outlier component) fitted on the same
training records. The last row is :func:`heliojax.prediction_d2`, what ``calibrate``
and ``aim`` predict. Prints JSON: the fractions of
records inside the nominal 68 % and 95 % regions, for the Gaussian (Mahalanobis
d^2 < 2.279, 5.991) and for the fitted law (:func:`heliojax.prediction_region_d2`), and
the median d^2 (1.386 for a correct Gaussian model).

    python benchmarks/predictive_coverage.py ../shared/data/paint
"""

from __future__ import annotations

import argparse
import json

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _ablation import add_holdout_fractions, apply_holdout_fractions  # noqa: E402 (benchmarks/)

import heliojax as hj  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", nargs="?", default=None, help="PAINT directory (default: the embedded subset)")
    add_holdout_fractions(ap)
    args = ap.parse_args()
    apply_holdout_fractions(args)
    fleet = hj.load_paint_directory(args.data_dir or hj.default_data_dir())
    run = hj.calibrate(fleet)
    padded = run.fleet
    r, s = hj.residual_prediction(run.result, padded, np.asarray(padded.mask))
    h = len(fleet.ids)
    r, s = np.asarray(r)[:h], np.asarray(s)[:h]
    noise = np.asarray(run.noise_mrad)[:h]
    converged = np.array([run.summary["heliostats"][i]["status"] == "converged" for i in fleet.ids])
    held_out = np.asarray(run.test_mask)[:h] & converged[:, None]
    days = hj.days_since_fit(
        run.train_mask & ~run.superseded, np.asarray(padded.context.unix_time), np.asarray(padded.context.unix_time)
    )[:h]
    drift = float(run.predictive["drift_mrad2_per_day"]) * np.nan_to_num(days)
    law = hj.PointingErrorLaw.from_dict(run.predictive["error_law"])
    out = {
        "benchmark": "predictive_coverage",
        "data": str(args.data_dir or "embedded"),
        "heliostats": h,
        "predictive": run.summary["predictive"],
    }
    rows = {
        name: np.einsum("hmi,hmij,hmj->hm", r, np.linalg.inv(total + 1e-12 * np.eye(2)), r)
        for name, total in (
            ("parameters_only", s),
            ("parameters_and_noise", s + noise[:, None, None, None] ** 2 * np.eye(2)),
            ("parameters_noise_and_drift", s + (noise[:, None] ** 2 + drift)[..., None, None] * np.eye(2)),
        )
    }
    rows["parameters_noise_drift_and_sky_gap"] = np.asarray(hj.prediction_d2(run))[:h]
    for name, d2 in rows.items():
        use = held_out & np.isfinite(d2)
        out[name] = {"held_out_records": int(use.sum()), "median_d2": float(np.median(d2[use]))}
        for name_law, fitted in (("gaussian", hj.PointingErrorLaw()), ("fitted_law", law)):
            x68, x95 = hj.prediction_region_d2(0.68, fitted), hj.prediction_region_d2(0.95, fitted)
            per = [float(np.mean(d2[i][use[i]] < x95)) for i in range(h) if use[i].any()]
            out[name][name_law] = {
                "coverage_68": float(np.mean(d2[use] < x68)),
                "coverage_95": float(np.mean(d2[use] < x95)),
                "per_heliostat_coverage_95_min_median": [min(per), float(np.median(per))],
            }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
