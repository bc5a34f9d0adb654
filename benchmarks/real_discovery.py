"""Issue 13, item 6: what discovery finds on the real PAINT records, and whether the
named effects lower the held-out error on the time split.

    python benchmarks/real_discovery.py [--paint ../shared/data/paint] [--report report.json]

1. ``heliojax.discover`` (base ``auto``) on every record; or read its ``report.json``.
2. For the base model and for the base plus the first k named library effects
   (k = 1..K, at the amplitudes discovery reported, held fixed): the default
   calibration (robust, pooled, change-point aware) on the time split, i.e. trained on
   each heliostat's earlier records and evaluated on its later ones.
3. Temporal generalisation: the held-out beam error against the days since the
   heliostat's last training record (bins 0-30, 30-90, 90-180, > 180 days) and
   against the sun's angular distance from the heliostat's training suns (rank
   correlations; ``--figure`` plots both), and for heliostats with and without a
   change point.

Shared effects only (a per-heliostat effect has no one value to hold fixed). Prints JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
from scipy import stats

import heliojax as hj
from heliojax._errors import ConfigError
from heliojax.cli._common import check_output_paths
from heliojax.discovery import discover
from heliojax.effects import add_effects, make_effect, with_data_references

BINS_DAYS = (0.0, 30.0, 90.0, 180.0, np.inf)
DERIVED = ("wobble_amplitude_1", "wobble_amplitude_2")  # reported, not parameters


def _stats(err: np.ndarray) -> dict:
    e = err[np.isfinite(err)]
    if not e.size:
        return {"n": 0}
    return {
        "n": int(e.size),
        "median_mrad": float(np.median(e)),
        "p90_mrad": float(np.percentile(e, 90)),
        "rms_mrad": float(np.sqrt(np.mean(e**2))),
    }


def _sun_distance_deg(sun: np.ndarray, train: np.ndarray) -> np.ndarray:
    """``(H, M)`` angle (deg) between each record's sun and the nearest training sun
    of the same heliostat."""
    cos = np.einsum("hmk,hnk->hmn", sun, sun)
    cos = np.where(train[:, None, :], cos, -1.0)
    return np.degrees(np.arccos(np.clip(cos.max(axis=-1), -1.0, 1.0)))


def time_split_errors(fleet, model, figure: Path | None = None) -> dict:
    """Held-out beam error of the default calibration on the time split, overall,
    by days since each heliostat's last training record, and its rank correlation
    with the time since training and with the sun's distance from the training suns."""
    free = hj.default_free(model)
    if isinstance(model, hj.effects.EffectModel):  # discovered effects held at their values
        free = eqx.tree_at(lambda f: f.effects, free, hj.no_free(model).effects)
    run = hj.calibrate(fleet, model=model, split="time", fit_options={"free": free})
    h = len(fleet.ids)
    err = np.asarray(run.errors_mrad)[:h]
    test = np.asarray(run.test_mask)[:h]
    train = np.asarray(run.train_mask)[:h]
    t = np.asarray(run.fleet.context.unix_time)[:h]
    last_train = np.where(train, t, -np.inf).max(axis=1, keepdims=True)
    days = (t - last_train) / 86400.0
    out = {"held_out": _stats(np.where(test, err, np.nan))}
    out["by_days_since_training"] = {
        f"{lo:g}-{hi:g}": _stats(np.where(test & (days >= lo) & (days < hi), err, np.nan))
        for lo, hi in zip(BINS_DAYS[:-1], BINS_DAYS[1:])
    }
    out["train"] = _stats(np.where(train, err, np.nan))
    sun_deg = _sun_distance_deg(np.asarray(run.fleet.context.sun)[:h], train)
    ok = test & np.isfinite(err)
    out["spearman_error_vs_days"] = float(stats.spearmanr(days[ok], err[ok]).statistic)
    out["spearman_error_vs_sun_distance"] = float(stats.spearmanr(sun_deg[ok], err[ok]).statistic)
    out["spearman_days_vs_sun_distance"] = float(stats.spearmanr(days[ok], sun_deg[ok]).statistic)
    changed = np.array([bool(e.get("change_point")) for e in run.summary["heliostats"].values()])[:h]
    for name, sel in (("with_change_point", changed), ("without_change_point", ~changed)):
        out[f"held_out_{name}"] = _stats(np.where(test & sel[:, None], err, np.nan))
    if figure is not None:
        _plot(days, sun_deg, err, ok, changed, figure)
    return out


def _plot(days, sun_deg, err, ok, changed, path: Path) -> None:
    from heliojax._plotting import pyplot, save_figure

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), sharey=True)
    for ax, x, label in (
        (axes[0], days, "days since the heliostat's last training record"),
        (axes[1], sun_deg, "sun's angular distance from the nearest training sun [deg]"),
    ):
        for sel, colour, name in ((~changed, "C0", "heliostats without"), (changed, "C1", "heliostats with")):
            m = ok & sel[:, None]
            ax.scatter(x[m], err[m], s=9, alpha=0.6, color=colour, label=f"held-out records, {name} a change point")
        xv, ev = x[ok], err[ok]
        edges = np.unique(np.quantile(xv, np.linspace(0, 1, 9)))
        idx = np.clip(np.searchsorted(edges, xv, side="right") - 1, 0, len(edges) - 2)
        centres = [np.median(xv[idx == i]) for i in range(len(edges) - 1)]
        medians = [np.median(ev[idx == i]) for i in range(len(edges) - 1)]
        ax.plot(centres, medians, "k-o", ms=4, label="median in octile bins (all records)")
        ax.set_xlabel(label)
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("held-out beam error [mrad]")
    axes[0].legend(fontsize=8, loc="upper right")
    fig.suptitle("time split, default calibration (robust, pooled, change-point aware) on ../shared/data/paint")
    fig.tight_layout()
    save_figure(fig, path)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--paint", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/paint")
    p.add_argument("--report", type=Path, default=None, help="discovery report.json to use (default: run discovery)")
    p.add_argument("--figure", type=Path, default=None, help="PNG: held-out error against time and sun distance")
    args = p.parse_args()
    try:  # before the work: a folder or an unwritable place named as the output had failed after it
        check_output_paths(args, ("figure",))
    except ConfigError as e:
        p.error(str(e))
    jax.config.update("jax_enable_x64", True)  # calibration precision
    fleet = hj.load_paint_directory(args.paint)
    t0 = time.perf_counter()
    if args.report is None:
        report = discover(fleet, base="auto").report
        seconds = time.perf_counter() - t0
    else:
        report = json.loads(args.report.read_text())
        seconds = None
    base = hj.nominal_model("auto", fleet.counts.dtype)
    rows = [{"model": "auto", **time_split_errors(fleet, base, args.figure)}]
    effects = []
    for s in report["steps"]:
        if s["mode"] != "shared":
            continue
        values = {k: v for k, v in s["amplitude"].items() if k not in DERIVED and v is not None}
        effects.append(make_effect(s["effect"], base, **values))
        model = with_data_references(add_effects(base, effects), fleet)
        rows.append({"model": "auto + " + " + ".join(e.NAME for e in effects), **time_split_errors(fleet, model)})
    out = {
        "data": str(args.paint),
        "discovery_seconds": seconds,
        "named_effects": report["named_effects"],
        "steps": [
            {k: s[k] for k in ("effect", "mode", "amplitude", "implausible", "cv_log_ratio") if k in s}
            for s in report["steps"]
        ],
        "change_points": [(c["heliostat"], c["time"][:10]) for c in report["change_points"]],
        "n_outliers": len(report["outliers"]),
        "unexplained": [(u["variable"], u["p_holm"], u["effect_size_mrad"]) for u in report["unexplained"]],
        "cv_heldout_median_mrad": [report["heldout_median_base_mrad"], report["heldout_median_final_mrad"]],
        "time_split": rows,
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
