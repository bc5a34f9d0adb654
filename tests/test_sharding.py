"""Sharded and multi-process fleet calibration equal the single-device fit.

Several devices on one CPU need ``XLA_FLAGS=--xla_force_host_platform_device_count``
before JAX is imported, and ``jax.distributed`` needs fresh processes: both run in
subprocesses that read the same fleet from an npz written here.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax import FitStatus, forward, process_slice, reflected_ray
from heliojax._simulate import random_stone_models, synthetic_geometry
from heliojax._xla_flags import with_fast_cpu_compilation

REPO = Path(__file__).resolve().parents[1]
FIELDS = ("params", "std", "covariance", "status", "n_steps", "n_used", "rms_mrad", "cost", "noise_mrad")
SEED = 7

# Loads the fleet written by `_write_fleet` (geometry rebuilt from the same key);
# `load(slice)` returns the Fleet of those heliostats only.
LOADER = """
import numpy as np, jax
import heliojax as hj
from heliojax._simulate import synthetic_geometry
with np.load(NPZ) as _npz:
    _z = dict(_npz)
H = _z["counts"].shape[0]
STONE = hj.StoneModel.nominal(np.float64)
_geometry = synthetic_geometry(jax.random.PRNGKey(int(_z["seed"])), H)
def load(sl=slice(None)):
    return hj.fleet_from_arrays(
        jax.tree.map(lambda x: x[sl], _geometry), _z["counts"][sl], hj.RecordContext.from_sun(_z["sun"][sl]),
        _z["focal"][sl], _z["mask"][sl])
def save(path, res, **extra):
    arrays = {k: np.asarray(res.parameters() if k == "params" else getattr(res, k)) for k in FIELDS}
    np.savez(path, **arrays, **extra)
"""


def _write_fleet(path: Path, h: int = 6, m: int = 12) -> None:
    """Records of random true Stone models: random counts and suns, spot = mirror
    centre + 150 m along the true reflected ray + 3 cm noise. Heliostat 1 keeps
    4 records (too few for 8 parameters), heliostat 3 has a NaN record."""
    rng = np.random.default_rng(SEED)
    g = synthetic_geometry(jax.random.PRNGKey(SEED), h)
    true = random_stone_models(jax.random.PRNGKey(SEED + 1), h)
    counts = rng.uniform(15000, 55000, (h, m, 2)).round()
    az = rng.uniform(-1.2, 1.2, (h, m))
    el = rng.uniform(0.3, 1.1, (h, m))
    sun = np.stack([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)], -1)

    def spot(model, gi, c, s):
        pose = forward(model, gi, c)
        return pose.centre + 150.0 * reflected_ray(pose, s)

    per_h = lambda mo, gi, c, s: jax.vmap(lambda cc, ss: spot(mo, gi, cc, ss))(c, s)  # noqa: E731
    focal = np.asarray(jax.jit(jax.vmap(per_h))(true, g, jnp.asarray(counts), jnp.asarray(sun)))
    focal = focal + rng.normal(0.0, 0.03, focal.shape)
    mask = np.ones((h, m), bool)
    mask[1, 4:] = False
    counts[3, 5, 0] = np.nan
    np.savez(path, counts=counts, sun=sun, focal=focal, mask=mask, seed=SEED)


def _load_here(npz: Path, sl=slice(None)) -> hj.Fleet:
    scope = {"NPZ": str(npz), "FIELDS": FIELDS}
    exec(LOADER, scope)
    return scope["load"](sl)


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_PLATFORMS")}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env["JAX_PLATFORMS"] = "cpu"
    env.update(extra)
    # the suite's faster-compiling CPU emitters (tests/conftest.py), beside the test's own flags
    env["XLA_FLAGS"] = with_fast_cpu_compilation(extra.get("XLA_FLAGS", ""))
    return env


PATH_ATOL = 10 * hj.fitting.DEFAULT_ATOL * 1e-2
"""Parameters (rad, or dimensionless gear ratios) of fits that reach the same optimum
by different floating-point paths: 10x the solver's step tolerance in scaled units
times the parameter scale (1e-2). One process's ``lax.map`` and another's sharded
``vmap`` are different XLA programs; with their rounding the LM paths may differ
(a fresh clone without ``../shared`` ran heliostats 0 and 4 in 7 and 15 steps here,
13 and 8 sharded; every other field agreed)."""


def _assert_same(ref: dict, got: dict, what: str) -> None:
    for k in FIELDS:
        a, b = np.asarray(ref[k]), np.asarray(got[k])
        assert a.shape == b.shape, (what, k, a.shape, b.shape)
        if k == "params":
            np.testing.assert_allclose(b, a, rtol=0, atol=PATH_ATOL, equal_nan=True, err_msg=f"{what}: {k}")
        elif k == "n_steps":  # the path, not the result: may differ with the rounding
            continue
        elif a.dtype.kind == "f":  # statistics at the optimum: as close as the optimum
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-12, equal_nan=True, err_msg=f"{what}: {k}")
        else:
            np.testing.assert_array_equal(b, a, err_msg=f"{what}: {k}")


@pytest.fixture(scope="module")
def fleet_npz(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sharding") / "fleet.npz"
    _write_fleet(path)
    return path


@pytest.fixture(scope="module")
def four_device_run(fleet_npz, tmp_path_factory):
    """Starts the sharded fit on four simulated CPU devices in a subprocess (it
    compiles while this process computes the reference)."""
    out = tmp_path_factory.mktemp("four") / "sharded.npz"
    script = LOADER + textwrap.dedent(
        """
        import jax.numpy as jnp
        from heliojax.fitting import _batching
        assert len(jax.devices()) == 4, jax.devices()
        shards = []
        _put = jax.device_put
        def spy(x, s=None, **kw):  # the placements with a sharding (others put host arrays on the default device)
            y = _put(x, s, **kw)
            if s is not None:
                shards.append(max(len(l.sharding.device_set) for l in jax.tree.leaves(y)))
            return y
        _batching.jax.device_put = spy
        res = hj.fit(STONE, load(), batching=hj.Sharded())
        _batching.jax.device_put = _put
        save(OUT, res, n_devices=len(jax.devices()), n_shards=min(shards))
        """
    )
    code = (
        "import jax; jax.config.update('jax_enable_x64', True)\n"
        f"NPZ={str(fleet_npz)!r}\nOUT={str(out)!r}\nFIELDS={FIELDS!r}\n" + script
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        env=_env(XLA_FLAGS="--xla_force_host_platform_device_count=4"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    yield proc, out
    if proc.poll() is None:
        proc.kill()
    proc.communicate(timeout=10)  # reaps the process and closes its pipes, wherever the test ran


@pytest.fixture(scope="module")
def reference(fleet_npz) -> dict:
    """Single-device fit in this process."""
    res = hj.fit(hj.StoneModel.nominal(np.float64), _load_here(fleet_npz))
    return {k: np.asarray(res.parameters() if k == "params" else getattr(res, k)) for k in FIELDS}


def test_reference_statuses(reference):
    status = [FitStatus(int(s)) for s in reference["status"]]
    assert status[1] is FitStatus.TOO_FEW_RECORDS
    # never reported, so never iterated on: its solve stops at once, it has no noise or RMS
    assert reference["n_steps"][1] <= 2 < reference["n_steps"][0]
    assert np.isnan(reference["rms_mrad"][1]) and np.isnan(reference["noise_mrad"][1])
    assert status[3] is FitStatus.NON_FINITE_INPUT
    assert status[0] is FitStatus.CONVERGED


@pytest.mark.parametrize(
    ("n", "p", "expected"),
    [(10, 3, [(0, 4), (4, 7), (7, 10)]), (2, 3, [(0, 1), (1, 2), (2, 2)]), (6, 1, [(0, 6)]), (0, 2, [(0, 0), (0, 0)])],
)
def test_process_slice(n, p, expected):
    got = [process_slice(n, i, p) for i in range(p)]
    assert [(s.start, s.stop) for s in got] == expected
    assert sum(s.stop - s.start for s in got) == n


def test_process_slice_rejects_bad_index():
    with pytest.raises(ValueError):
        process_slice(5, 2, 2)


def test_sharded_over_four_cpu_devices(four_device_run, reference):
    """Four simulated CPU devices (6 heliostats: padded to 8), against the
    single-device fit of this process."""
    proc, out = four_device_run
    try:
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, err[-4000:]
    with np.load(out) as npz:
        got = dict(npz)
    assert int(got["n_devices"]) == 4
    assert int(got["n_shards"]) == 4  # the inputs really were spread over 4 devices
    _assert_same(reference, got, "4 devices")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_processes_on_loopback(fleet_npz, reference, tmp_path):
    """jax.distributed with two CPU processes on 127.0.0.1 (gloo collectives):
    each loads only its process_slice, both end with the full, identical result."""
    port = _free_port()
    init = textwrap.dedent(
        """
        jax.distributed.initialize(coordinator_address=f"127.0.0.1:{PORT}", num_processes=2,
                                   process_id=PID, initialization_timeout=60)
        """
    )
    worker = (
        init
        + LOADER
        + textwrap.dedent(
            """
        from heliojax import calibrate_distributed, process_slice
        seen = []
        def load_logged(sl):
            seen.append((sl.start, sl.stop))
            return load(sl)
        res = calibrate_distributed(load_logged, STONE, H)
        save(OUT, res, process_count=jax.process_count(), loaded=np.asarray(seen[0]))
        jax.distributed.shutdown()
        """
        )
    )
    procs = []
    try:
        for pid in range(2):
            code = (
                "import jax; jax.config.update('jax_enable_x64', True)\n"
                f"jax.config.update('jax_cpu_collectives_implementation', 'gloo')\n"
                f"NPZ={str(fleet_npz)!r}\nOUT={str(tmp_path / f'p{pid}.npz')!r}\nFIELDS={FIELDS!r}\n"
                f"PORT={port}\nPID={pid}\n" + worker
            )
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-c", code], env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
                )
            )
        logs = [p.communicate(timeout=240) for p in procs]
        for p, (_, err) in zip(procs, logs):
            assert p.returncode == 0, err[-4000:]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.communicate(timeout=10)
    h = reference["status"].shape[0]
    for pid in range(2):
        with np.load(tmp_path / f"p{pid}.npz") as npz:
            got = dict(npz)
        assert int(got["process_count"]) == 2
        sl = process_slice(h, pid, 2)
        assert tuple(got["loaded"]) == (sl.start, sl.stop)  # loaded only its own slice
        _assert_same(reference, got, f"process {pid}")
