"""CLI: python -m independent_sim --effect NAME --amplitude X --seed S --out DIR [--outliers 0.05]."""

from __future__ import annotations

import argparse
import json

from ._effects import EFFECTS
from ._generate import DEFAULT_SOURCE, NOISE_KINDS, generate


def main(argv=None) -> None:
    p = argparse.ArgumentParser(prog="independent_sim", description=__doc__)
    p.add_argument("--effect", required=True, choices=sorted(EFFECTS))
    p.add_argument("--amplitude", type=float, default=None, help="in the effect's unit (see README)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--outliers", type=float, default=0.0)
    p.add_argument("--noise", type=float, default=0.25, help="camera noise, mrad per component")
    p.add_argument("--noise-kind", choices=NOISE_KINDS, default="gaussian", help="the camera noise's law")
    p.add_argument("--heliostats", type=int, default=20)
    p.add_argument("--records", type=int, default=60)
    p.add_argument("--controller", choices=["calibrated", "nominal"], default="calibrated")
    p.add_argument("--source", default=str(DEFAULT_SOURCE))
    a = p.parse_args(argv)
    truth = generate(
        a.effect,
        a.out,
        seed=a.seed,
        amplitude=a.amplitude,
        n_heliostats=a.heliostats,
        n_records=a.records,
        noise_mrad=a.noise,
        outliers=a.outliers,
        controller=a.controller,
        source=a.source,
        noise_kind=a.noise_kind,
    )
    print(json.dumps({k: truth[k] for k in ("effect", "beam_rms_mrad", "seed")}))


if __name__ == "__main__":
    main()
