"""The retrospective planning study (``benchmarks/planning_study.py``) on suites of
the independent simulator (``independent_sim/``, shares no code with heliojax): does
planning for a model that is not exact (:func:`heliojax.discrepancy_design`) choose
better records than the exact-model planner, time order and chance when the plant
has an effect the actuator model lacks?

Each suite: 20 real Jülich heliostats x 60 records at real sun positions and times,
drawn plant errors, 0.25 mrad camera noise, one hidden effect at its default
amplitude (``none``: the null suite, where the model is exact and the discrepancy
planner should do no worse). The study's protocol is unchanged (pool: each
heliostat's records before its 70 % time quantile; test: the later ones; K = 4, 6,
8, 12, 16; 20 random draws).

    python benchmarks/independent_planning.py --effects none gravity_sag encoder_wobble --seeds 1 2

Prints JSON: per effect and seed the study's table and the learnt discrepancy;
progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from planning_coverage import true_components  # noqa: E402
from planning_study import BUDGETS, PLANNERS, study  # noqa: E402

import heliojax as hj  # noqa: E402
import independent_sim  # noqa: E402
from heliojax.cli._common import integer, number  # noqa: E402
from heliojax.optics import target_from_tower  # noqa: E402

METHODS = (*PLANNERS, "first_in_time", "random")


def operation_errors(suite: Path, lanes: dict, seed: int, instants: int = 40) -> dict:
    """The planner's own objective, judged by the truth: every lane's fitted model aims at
    the receiver at ``instants`` random daylight instants of a year (``heliojax.aim_fleet``),
    and the simulator's own kinematics (``independent_sim.plant_mount``; the whole truth of
    a null suite) gives the true beam error of those counts. Per K and method: the median
    over heliostats of each heliostat's RMS operating error (random: median over draws)."""

    fleet = hj.load_paint_directory(suite)
    receiver = np.asarray(
        target_from_tower(hj.read_tower(next(suite.glob("*-tower-measurements.json"))), "receiver").centre
    )
    rng = np.random.default_rng(seed)
    unix = hj.datetime_to_unix("2024-01-01T00:00:00Z") + rng.uniform(0, 366 * 86400.0, 10 * instants)
    position = hj.solar_position(jnp.asarray(unix), *np.asarray(fleet.origin_lla))
    up = np.asarray(position.elevation) > np.radians(15.0)
    sun = np.asarray(position.direction_enu())[up][:instants]
    keys = lanes["keys"]
    n = len(keys)
    take = lambda x: x[:n]  # noqa: E731
    model, geometry = jax.tree.map(take, lanes["model"]), jax.tree.map(take, lanes["geometry"])
    aim = hj.aim_fleet(model, geometry, jnp.asarray(sun), jnp.asarray(receiver))
    counts, ok = np.asarray(aim.counts), np.asarray(aim.ok)
    mounts = {hid: independent_sim.plant_mount(suite, hid) for hid in {k[0] for k in keys}}
    rms = np.full(n, np.nan)
    for lane, key in enumerate(keys):  # benchmark bookkeeping, numpy truth per lane
        err = true_components(mounts[key[0]], counts[lane], sun, receiver)
        use = ok[lane] & np.all(np.isfinite(err), axis=-1)
        rms[lane] = np.sqrt(np.mean(np.sum(err[use] ** 2, axis=-1))) if use.any() else np.nan
    out = {}
    for k in BUDGETS:
        row = {}
        for method in (*PLANNERS, "first", "random"):
            per = {}
            for lane, key in enumerate(keys):
                if key[1] == k and key[2] == method:
                    per.setdefault(key[0], []).append(rms[lane])
            row[method] = round(float(np.nanmedian([np.nanmedian(v) for v in per.values()])), 3)
        out[str(k)] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--effects", nargs="+", default=["none", "gravity_sag", "encoder_wobble"])
    ap.add_argument("--seeds", type=integer(0), nargs="+", default=[1, 2])
    ap.add_argument("--heliostats", type=integer(1), default=20)
    ap.add_argument("--records", type=integer(1), default=60)
    ap.add_argument("--amplitude", type=number(), default=None, help="every effect's amplitude (default: its own)")
    ap.add_argument(
        "--noise-kind",
        default="gaussian",
        choices=independent_sim.NOISE_KINDS,
        help="the camera noise's law ('daily': half its variance shared by the records of one day)",
    )
    args = ap.parse_args()
    t0 = time.perf_counter()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for effect in args.effects:
            for seed in args.seeds:
                suite = Path(tmp) / f"{effect}-{seed}"
                amplitude = None if effect == "none" else args.amplitude
                independent_sim.generate(
                    effect,
                    suite,
                    seed=seed,
                    amplitude=amplitude,
                    n_heliostats=args.heliostats,
                    n_records=args.records,
                    noise_kind=args.noise_kind,
                )
                out = study(suite, min_records=int(0.5 * args.records), seed=seed, keep_lanes=effect == "none")
                table = {k: {m: round(out["table"][str(k)][f"{m}_mrad"], 3) for m in METHODS} for k in BUDGETS}
                runs.append(
                    {
                        "effect": effect,
                        "seed": seed,
                        "discrepancy": out["discrepancy"],
                        "drift_mrad2_per_day": out["drift_mrad2_per_day"],
                        "intra_day_correlation": out["intra_day_correlation"]["intra_day_correlation"],
                        "table": table,
                    }
                )
                if effect == "none":
                    runs[-1]["operation"] = operation_errors(suite, out.pop("_lanes"), seed)
                print(f"{effect} seed {seed}: {json.dumps(runs[-1])}", file=sys.stderr)
    # per effect: mean over seeds of each method's fleet median, and how often each planner beats random
    summary = {}
    for effect in args.effects:
        rows = [r for r in runs if r["effect"] == effect]
        summary[effect] = {
            str(k): {m: round(sum(r["table"][k][m] for r in rows) / len(rows), 3) for m in METHODS} for k in BUDGETS
        }
    print(json.dumps({"benchmark": "independent_planning", "amplitude": args.amplitude, "noise_kind": args.noise_kind,
                      "summary_mean_over_seeds": summary, "runs": runs,
                      "wall_s": round(time.perf_counter() - t0, 1)}, indent=2))  # fmt: skip


if __name__ == "__main__":
    main()
