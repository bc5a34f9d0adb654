"""Baseline for issue 13: heliojax discovery (black box, CLI) on suites of the independent simulator.

    PYTHONPATH=$PWD python benchmarks/independent_discovery.py --work /tmp/isd --seed 101 [--effects a,b]
    PYTHONPATH=$PWD python benchmarks/independent_discovery.py --work /tmp/isd --table-only

Each suite: 20 real heliostats x 60 records, noise 0.25 mrad, one hidden effect (tag `<effect>_out`: with
5 % gross outliers). Prints a Markdown table: truth vs what discovery names.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from independent_sim import EFFECTS, generate  # noqa: E402 (after the sys.path line)

DEFAULT = [
    "none",
    "backlash",
    "encoder_wobble",
    "gravity_sag",
    "step",
    "thermal",
    "clock",
    "lens_distortion",
    "wind_direction",
    "daily_periodic",
    "survey_target",
    "backlash_out",
    "actuator_geometry",
    "wind",
    "refraction",
    "survey_heliostat",
]


def run_suite(work: Path, tag: str, seed: int) -> None:
    effect, outliers = (tag[:-4], 0.05) if tag.endswith("_out") else (tag, 0.0)
    generate(effect, work / tag, seed=seed, outliers=outliers)
    subprocess.run(
        [
            sys.executable,
            "-m",
            "heliojax.cli._main",
            "discover",
            str(work / tag),
            "--base",
            "actuator",
            "--report",
            str(work / f"{tag}.report.json"),
            "--quiet",
        ],
        check=False,
        stdout=subprocess.DEVNULL,
    )


def table(work: Path) -> str:
    lines = [
        (
            "| hidden effect (truth) | in library | beam RMS of effect (mrad) | named (in order; first step's "
            "amplitudes) | not identifiable | noise estimate (mrad) | held-out RMS base -> final (mrad) |"
        ),
        "|---|---|---|---|---|---|---|",
    ]
    for tag in DEFAULT:
        rep_path, truth_path = work / f"{tag}.report.json", work / tag / "truth.json"
        if not (rep_path.exists() and truth_path.exists()):
            continue
        rep, truth = json.loads(rep_path.read_text()), json.loads(truth_path.read_text())
        amp = truth["parameters"]["amplitude"]
        name = f"{truth['effect']} {amp:g} {EFFECTS[truth['effect']].unit}" if amp else truth["effect"]
        if truth["outlier_fraction"]:
            name += f", {truth['outlier_fraction']:.0%} outliers"
        named = ", ".join(rep.get("named_effects", [])) or "-"
        if rep.get("steps"):
            first = rep["steps"][0]
            amps = ", ".join(
                f"{k} {v * 1e3:.3g}" if first.get("units", {}).get(k) == "rad" else f"{k} {v:.3g}"
                for k, v in first.get("amplitude", {}).items()
            )
            named += f" ({amps})"
        lines.append(
            f"| {name} | {'yes' if truth['in_library'] else 'no'} | {truth['beam_rms_mrad']:.2f} | {named} "
            f"| {', '.join(rep.get('not_identifiable', [])) or '-'} "
            f"| {rep.get('noise_estimate_mrad', float('nan')):.3f} "
            f"| {rep['heldout_rms_base_mrad']:.3f} -> {rep['heldout_rms_final_mrad']:.3f} |"
        )
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--work", type=Path, required=True)
    p.add_argument("--seed", type=int, default=101)
    p.add_argument("--effects", default=",".join(DEFAULT))
    p.add_argument("--table-only", action="store_true")
    a = p.parse_args()
    if not a.table_only:
        for tag in a.effects.split(","):
            run_suite(a.work, tag, a.seed)
    print(table(a.work))


if __name__ == "__main__":
    main()
