"""Change points (issue 12, item 3) on suites of the independent simulator.

    python benchmarks/independent_change_points.py [--source ../shared/data/paint] [--seeds 1,2] [--null-seeds 3]

`independent_sim` (no heliojax code) writes PAINT-layout suites of 20 real
heliostats x 60 records (0.25 mrad noise) whose joint zeros jump by
``--amplitude`` mrad at a random date per heliostat (its ``step`` effect); the
null suites have no jump. heliojax loads each suite, fits it robustly
(actuator model) and scans for change points
(:func:`heliojax.fitting.find_change_points`). Prints one JSON object per suite:
jumps found, dated within the neighbouring records or +-10 days, the median
error of the estimated jump, and (null suites) the heliostats flagged.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import jax
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
import heliojax as hj  # noqa: E402
from heliojax.cli._common import number  # noqa: E402
from independent_sim import generate  # noqa: E402 (after the sys.path line)

DAY_S = 86400.0


def run_suite(source: Path, seed: int, amplitude_mrad: float) -> dict:
    with tempfile.TemporaryDirectory() as d:
        truth = generate("step", d, seed=seed, amplitude=amplitude_mrad, source=source)
        fleet = hj.load_paint_directory(d)
    robust = hj.fitting.fit_robust(hj.ActuatorModel.nominal(), fleet)
    cp = hj.fitting.find_change_points(robust.solution, fleet, fleet.mask, robust.weights)
    per = truth["parameters"]["per_heliostat"]
    found = np.asarray(cp.found)
    before, after, jump = np.asarray(cp.previous_time_s), np.asarray(cp.time_s), np.asarray(cp.jump_mrad)
    dated, err = [], []
    for i, h in enumerate(fleet.ids):
        if not found[i]:
            continue
        t = per[h]["step_unix"]
        dated.append(bool(before[i] < t <= after[i] or abs(after[i] - t) <= 10 * DAY_S))
        err.append(float(np.hypot(*(jump[i] - [per[h]["jump_axis_1_mrad"], per[h]["jump_axis_2_mrad"]]))))
    return {
        "amplitude_mrad": amplitude_mrad,
        "seed": seed,
        "heliostats": len(fleet.ids),
        "statuses": sorted(set(robust.solution.status_labels())),
        "found": int(found.sum()),
        "labelled_step": int((found & np.asarray(cp.is_step)).sum()),
        "dated": int(sum(dated)),
        "median_jump_error_mrad": float(np.median(err)) if err else None,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", type=Path, default=ROOT.parent / "shared" / "data" / "paint")
    p.add_argument("--seeds", default="1,2")
    p.add_argument("--null-seeds", default="3")
    p.add_argument("--amplitude", type=number(0.0), default=1.5, help="jump norm, mrad")
    a = p.parse_args()
    jax.config.update("jax_enable_x64", True)
    for s in a.seeds.split(","):
        print(json.dumps(run_suite(a.source, int(s), a.amplitude)))
    for s in a.null_seeds.split(","):
        print(json.dumps(run_suite(a.source, int(s), 1e-9)))  # the step effect with a null jump


if __name__ == "__main__":
    main()
