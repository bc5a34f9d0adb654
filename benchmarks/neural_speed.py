"""Speed of heliojax.neural: 30 heliostats x 4000 physics-generated pretraining
points (paper variant: pretraining + fine-tuning; residual variant: fine-tuning),
all heliostats in one compiled program. Prints JSON (seconds; compile and run
separately; ``total_s`` is what a first run costs).

    .venv/bin/python benchmarks/neural_speed.py [--heliostats 30] [--records 100]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from heliojax._geometry import sun_direction  # noqa: E402
from heliojax._heliostat import RecordContext  # noqa: E402
from heliojax._kinematics import ActuatorModel, StoneModel, inverse_aim  # noqa: E402
from heliojax._simulate import calibration_target, synthetic_geometry  # noqa: E402
from heliojax.cli._common import integer  # noqa: E402
from heliojax.neural import NeuralConfig, heliostat_keys, init_residual_networks, validation_tail  # noqa: E402
from heliojax.neural._train import (  # noqa: E402
    _finetune_paper_program,
    _finetune_residual_program,
    _pretrain_paper_program,
    synthetic_fleet_data,
)


def _timed(fn, *args):
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    t1 = time.perf_counter()
    out = compiled(*args)
    jax.block_until_ready(out)
    t2 = time.perf_counter()
    return out, t1 - t0, t2 - t1


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--heliostats", type=integer(1), default=30)
    ap.add_argument("--records", type=integer(1), default=100)
    args = ap.parse_args()
    h, m = args.heliostats, args.records
    nn = NeuralConfig()
    key = jax.random.key(0)
    k_g, k_az, k_el = jax.random.split(key, 3)
    geometry = synthetic_geometry(k_g, h)
    target = calibration_target()
    sun = sun_direction(
        jax.random.uniform(k_az, (h, m), minval=-1.2, maxval=1.2),
        jax.random.uniform(k_el, (h, m), minval=0.3, maxval=1.1),
    )
    truth = ActuatorModel.nominal(jnp.float64)
    counts = jax.jit(jax.vmap(lambda g, s: jax.vmap(lambda si: inverse_aim(truth, g, target.centre, si))(s)))(
        geometry, sun
    )
    focal = jnp.broadcast_to(target.centre, (h, m, 3))
    context = RecordContext.from_sun(sun)
    base = jax.vmap(lambda _: StoneModel.nominal(jnp.float64))(jnp.arange(h))
    fit, val = validation_tail(np.ones((h, m), bool), nn.val_fraction)
    w_fit, w_val = jnp.asarray(fit, float), jnp.asarray(val, float)
    u = jnp.broadcast_to(target.u_axis, (h, m, 3))
    v = jnp.broadcast_to(target.v_axis, (h, m, 3))

    res = {
        "heliostats": h,
        "records_per_heliostat": m,
        "pretraining_points": nn.n_synthetic,
        "pretrain_steps": nn.pretrain_epochs * nn.steps_per_epoch,
        "batch_size": nn.batch_size,
        "finetune_steps": nn.finetune_epochs,
        "residual_steps": nn.residual_epochs,
        "backend": jax.default_backend(),
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
    }
    syn, c0, r0 = _timed(synthetic_fleet_data, heliostat_keys(key, h), base, geometry, sun, focal, u, v, w_fit, nn)
    (preds, _), c1, r1 = _timed(_pretrain_paper_program, heliostat_keys(jax.random.key(1), h), syn, nn)
    _, c2, r2 = _timed(
        _finetune_paper_program, heliostat_keys(jax.random.key(2), h), preds, counts, sun, focal, w_fit, w_val, nn
    )
    res["paper"] = {
        "synthetic_compile_s": c0,
        "synthetic_run_s": r0,
        "pretrain_compile_s": c1,
        "pretrain_run_s": r1,
        "finetune_compile_s": c2,
        "finetune_run_s": r2,
        "compile_s": c0 + c1 + c2,
        "run_s": r0 + r1 + r2,
        "total_s": c0 + c1 + c2 + r0 + r1 + r2,
    }
    nets = init_residual_networks(jax.random.key(3), h, nn)
    scale = jnp.full((h,), 5e-3)
    _, c3, r3 = _timed(
        _finetune_residual_program,
        heliostat_keys(jax.random.key(4), h),
        nets,
        base,
        geometry,
        counts,
        context,
        focal,
        scale,
        w_fit,
        w_val,
        nn,
    )
    res["residual"] = {"compile_s": c3, "run_s": r3, "total_s": c3 + r3}
    res["paper_under_120_s"] = res["paper"]["total_s"] < 120.0
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
