"""Fleet calibration speed: heliojax ``fit_fleet`` against a scipy loop.

Usage::

    python benchmarks/calibration_speed.py --heliostats 1000 --records 100 --json
    python benchmarks/calibration_speed.py --heliostats 10000 --records 100 --skip-scipy --json
    python benchmarks/calibration_speed.py --heliostats 100000 --records 100 --skip-scipy --json  # GPU

What is compared (float64, Stone model, 8 parameters, no prior, same data):

* **heliojax**: :func:`heliojax.fit` (optimistix Levenberg-Marquardt of every
  heliostat in one compiled program; batching strategy per backend: ``lax.map`` on
  CPU, in one block of heliostats per core run from threads of its own
  (:class:`heliojax.Threaded`) where there are several, ``vmap`` on GPU,
  overridable with ``--strategy``; ``map`` is the one-core figure). The training records are
  padded to the library's shape buckets (``--no-pad`` fits the exact shape).
  ``compile_s`` is the first call minus the best later call (trace + lower + XLA
  compile); ``heliojax_s`` is the best of ``--repeats`` calls after the first.
  ``--cli-xla-flags`` compiles as the ``heliojax`` command does (XLA's older CPU
  fusion emitters; the JSON's ``xla_flags`` says which flags were in force).
* **scipy**: what a user would write instead: ``scipy.optimize.least_squares(
  method="lm")`` (MINPACK, forward-difference Jacobian, default tolerances) in a
  Python loop over heliostats, with the residual written in numpy (vectorised over
  a heliostat's records): :func:`stone_residual_np`, an independent implementation
  of the Stone chain of :mod:`heliojax._kinematics` (checked against heliojax to
  1e-12 in ``tests/test_benchmark_baseline.py``).

Data: :func:`heliojax.synthetic_geometry`, random true Stone models, random
calibration times over a year, :func:`heliojax.simulate_records` with Gaussian noise
of ``--noise`` mrad per tangent-plane component. Each heliostat's records are
chronological; the first 70 % train, the rest are held out (all records are
used, also those whose spot falls beside the 6 x 7 m target on its plane). Both fits are evaluated
with the same metric (:func:`heliojax.beam_errors_mrad`, the beam pointing angle)
on the held-out records.

With ``--scipy-heliostats K`` (or automatically when the estimated scipy time
exceeds ``--scipy-budget`` seconds) scipy runs on the first ``K`` heliostats only
and its time is extrapolated linearly; the JSON says so (``scipy_measured_heliostats``,
``scipy_extrapolated``).

Peak memory is ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of the benchmark
process: the data (simulated in a child process, ``--data`` keeps it in an npz for
reruns), the compilation and the fits (and scipy's unless ``--skip-scipy``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

from heliojax.cli._common import integer, number

# --------------------------------------------------------------------------------------
# The numpy baseline: Stone chain and beam error components (no JAX)
# --------------------------------------------------------------------------------------

STONE_NAMES = ("alpha", "beta", "gamma", "delta", "theta_k", "tau_k", "gr1", "gr2")
STONE_NOMINAL = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0])
STONE_SCALE = 1e-3  # solver units: mrad for angles, 1e-3 for gear ratios


def _rot_x(a):
    a = np.asarray(a, float)
    c, s = np.cos(a), np.sin(a)
    r = np.zeros(a.shape + (3, 3))
    r[..., 0, 0] = 1.0
    r[..., 1, 1] = c
    r[..., 1, 2] = -s
    r[..., 2, 1] = s
    r[..., 2, 2] = c
    return r


def _rot_y(a):
    a = np.asarray(a, float)
    c, s = np.cos(a), np.sin(a)
    r = np.zeros(a.shape + (3, 3))
    r[..., 0, 0] = c
    r[..., 0, 2] = s
    r[..., 1, 1] = 1.0
    r[..., 2, 0] = -s
    r[..., 2, 2] = c
    return r


def _rot_z(a):
    a = np.asarray(a, float)
    c, s = np.cos(a), np.sin(a)
    r = np.zeros(a.shape + (3, 3))
    r[..., 0, 0] = c
    r[..., 0, 1] = -s
    r[..., 1, 0] = s
    r[..., 1, 1] = c
    r[..., 2, 2] = 1.0
    return r


def stone_pose_np(params, geom, counts):
    """Mirror normals and centres ``(M, 3)`` of records ``counts (M, 2)``.

    ``params``: the 8 physical Stone parameters; ``geom``: dict with ``position``,
    ``joint_translation_1``, ``joint_translation_2``, ``concentrator_translation``
    (3,), ``linear_slope``, ``linear_intercept`` (2,). The chain (see
    ``heliojax._kinematics``)::

        n = Ry(alpha) Rz(beta) Rx(theta - pi/2) Ry(gamma) Rz(tau) Rx(delta) (0, -1, 0)
        c = P + V01 + Ry(alpha) Rz(beta) Rx(theta - pi/2) (V12 + Ry(gamma) Rz(tau) V2M)
        (theta, tau) = (slope * counts + intercept) / (gr1, gr2) + (theta_k, tau_k)
    """
    alpha, beta, gamma, delta, theta_k, tau_k, gr1, gr2 = params
    motor = geom["linear_slope"] * counts + geom["linear_intercept"]
    theta = motor[:, 0] / gr1 + theta_k
    tau = motor[:, 1] / gr2 + tau_k
    outer = (_rot_y(alpha) @ _rot_z(beta)) @ _rot_x(theta - np.pi / 2)  # (M, 3, 3)
    inner = _rot_y(gamma) @ _rot_z(tau)  # (M, 3, 3)
    n_2 = _rot_x(delta) @ np.array([0.0, -1.0, 0.0])  # normal in axis 2's frame
    normal = _matvec(outer, _matvec(inner, n_2))
    arm = geom["joint_translation_2"] + _matvec(inner, geom["concentrator_translation"])
    centre = geom["position"] + geom["joint_translation_1"] + _matvec(outer, arm)
    return normal, centre


def _matvec(a, v):
    return (a @ np.asarray(v)[..., None])[..., 0]


def _cross(a, b):
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        -1,
    )


def beam_components_np(normal, centre, sun, focal):
    """Tangent-plane beam error components ``(M, 2)`` (rad): ``(d . e1, d . e2)``
    with ``r`` the reflected ray, ``d`` the unit vector centre -> focal spot,
    ``e1 = normalize(up x r)``, ``e2 = r x e1``."""
    r = 2.0 * np.sum(sun * normal, -1, keepdims=True) * normal - sun
    d = focal - centre
    d /= np.sqrt(np.sum(d * d, -1, keepdims=True))
    e1 = np.stack([-r[:, 1], r[:, 0], np.zeros(len(r))], -1)  # (0, 0, 1) x r
    e1 /= np.sqrt(np.sum(e1 * e1, -1, keepdims=True))
    e2 = _cross(r, e1)
    return np.stack([np.sum(d * e1, -1), np.sum(d * e2, -1)], -1)


def stone_residual_np(y, geom, counts, sun, focal):
    """The least-squares residual ``(2 M,)`` in mrad of scaled parameters ``y``
    (physical = nominal + 1e-3 y)."""
    params = STONE_NOMINAL + STONE_SCALE * np.asarray(y)
    normal, centre = stone_pose_np(params, geom, counts)
    return 1e3 * beam_components_np(normal, centre, sun, focal).reshape(-1)


def scipy_fit_fleet(geoms, counts, sun, focal, mask, n_heliostats=None):
    """``scipy.optimize.least_squares(method="lm")`` per heliostat; returns
    ``(params (K, 8), n_fev (K,), seconds)`` for the first ``K`` heliostats."""
    from scipy.optimize import least_squares

    k = len(counts) if n_heliostats is None else int(n_heliostats)
    params = np.empty((k, 8))
    nfev = np.zeros(k, int)
    t0 = time.perf_counter()
    for i in range(k):
        m = mask[i]
        args = (geoms[i], counts[i][m], sun[i][m], focal[i][m])
        sol = least_squares(stone_residual_np, np.zeros(8), method="lm", args=args)
        params[i] = STONE_NOMINAL + STONE_SCALE * sol.x
        nfev[i] = sol.nfev
    return params, nfev, time.perf_counter() - t0


# --------------------------------------------------------------------------------------
# Simulated fleet
# --------------------------------------------------------------------------------------


def simulate_fleet(n, m, noise_mrad, seed=0, chunk=1000):
    """Simulated fleet as numpy pytrees: ``(geometry, true_params (n, 8), context,
    counts, focal, hit)``; simulated in jitted chunks of ``chunk`` heliostats (one
    compilation)."""
    import jax
    import jax.numpy as jnp

    from heliojax._simulate import (
        calibration_target,
        random_stone_models,
        simulate_records,
        synthetic_contexts,
        synthetic_geometry,
    )

    c = min(n, chunk)

    @jax.jit
    def one_chunk(key):
        k = jax.random.split(key, 4)
        g = synthetic_geometry(k[0], c)
        tm = random_stone_models(k[1], c)
        ctx = synthetic_contexts(k[2], c, m, weather=False)
        sim = simulate_records(k[3], tm, g, ctx, calibration_target(), noise_mrad=noise_mrad)
        true = jnp.stack([getattr(tm, f) for f in STONE_NAMES], -1)
        return g, true, ctx, sim.counts, sim.focal_spot, sim.mask

    base = jax.random.PRNGKey(seed)
    parts = [jax.tree.map(np.asarray, one_chunk(jax.random.fold_in(base, i))) for i in range((n + c - 1) // c)]
    out = jax.tree.map(lambda *xs: np.concatenate(xs, 0)[:n], *parts)
    return out


def save_fleet(path, fleet):
    """Write a :func:`simulate_fleet` tuple to ``path`` (npz of its leaves)."""
    import jax

    geometry, true, context, counts, focal, hit = fleet
    arrays = {f"g{i}": x for i, x in enumerate(jax.tree.leaves(geometry))}
    arrays.update({f"c{i}": x for i, x in enumerate(jax.tree.leaves(context))})
    tmp = str(path) + ".tmp.npz"
    np.savez(tmp, true=true, counts=counts, focal=focal, hit=hit, **arrays)
    os.replace(tmp, path)


def load_fleet(path):
    """Read what :func:`save_fleet` wrote (numpy leaves)."""
    import jax

    from heliojax._heliostat import HeliostatGeometry, LinearActuators, RecordContext

    with np.load(path) as npz:
        z = dict(npz)
    one = np.ones((1, 2))
    act = LinearActuators(*([one] * 8))
    g_tree = jax.tree.structure(HeliostatGeometry(*([np.ones((1, 3))] * 4), act, one, one, one))
    c_tree = jax.tree.structure(RecordContext.from_sun(np.ones((1, 1, 3))))
    g = jax.tree.unflatten(g_tree, [z[f"g{i}"] for i in range(g_tree.num_leaves)])
    c = jax.tree.unflatten(c_tree, [z[f"c{i}"] for i in range(c_tree.num_leaves)])
    return g, z["true"], c, z["counts"], z["focal"], z["hit"]


def _geom_dicts(geometry):
    fields = (
        "position",
        "joint_translation_1",
        "joint_translation_2",
        "concentrator_translation",
        "linear_slope",
        "linear_intercept",
    )
    arrays = {f: np.asarray(getattr(geometry, f)) for f in fields}
    n = arrays["position"].shape[0]
    return [{f: arrays[f][i] for f in fields} for i in range(n)]


# --------------------------------------------------------------------------------------
# heliojax
# --------------------------------------------------------------------------------------


def _take_records(tree, idx):
    import jax

    return jax.tree.map(lambda x: x[:, idx], tree)


def _pad(x, n_h, n_m, axis_m=True):
    """Pad axis 0 to ``n_h`` (copies of row 0) and axis 1 to ``n_m`` (copies of
    column 0) in numpy."""
    h = x.shape[0]
    if n_h > h:
        x = np.concatenate([x, np.repeat(x[:1], n_h - h, 0)], 0)
    if axis_m and x.ndim >= 2 and n_m > x.shape[1]:
        x = np.concatenate([x, np.repeat(x[:, :1], n_m - x.shape[1], 1)], 1)
    return x


def heliojax_data(geometry, context, counts, focal, mask, pad=True):
    """:class:`heliojax.Fleet` of the training records, padded to the shape buckets
    (numpy padding: no compilation per shape)."""
    import jax

    import heliojax as hj
    from heliojax._fleet import bucket_size

    h, m = counts.shape[:2]
    nh, nm = (bucket_size(h), bucket_size(m)) if pad else (h, m)
    geometry = jax.tree.map(lambda x: _pad(np.asarray(x), nh, nm, axis_m=False), geometry)
    context = jax.tree.map(lambda x: _pad(np.asarray(x), nh, nm), context)
    mask = _pad(np.asarray(mask), nh, nm)
    mask[h:] = False
    mask[:, m:] = False
    data = hj.fleet_from_arrays(
        jax.device_put(geometry),
        jax.device_put(_pad(np.asarray(counts), nh, nm)),
        jax.device_put(context),
        jax.device_put(_pad(np.asarray(focal), nh, nm)),
        jax.device_put(mask),
    )
    return data


def lm_solver(linear_solver: str):
    """The Levenberg-Marquardt solver of the fit: heliojax's default for the backend
    (``"auto"``: QR on CPU, Cholesky on accelerators), or with the damped step solved
    by QR of the stacked Jacobian (``"qr"``, the CPU default) or by Cholesky of the
    normal equations (``"cholesky"``, the accelerators' default: 8 x 8 systems instead
    of a QR of a (2M + 8) x 8 matrix per heliostat and step)."""
    from heliojax.fitting import default_solver

    backends = {"auto": None, "qr": "cpu", "cholesky": "gpu"}
    if linear_solver not in backends:
        raise SystemExit(f"--linear-solver: unknown {linear_solver!r} (auto, qr or cholesky)")
    return default_solver(backends[linear_solver])


def batching_of(strategy: str, chunk_size: int):
    """The library's batching strategy of that name, or ``"vmap-restart"``: vmap with
    the straggler restart of the accelerators' default."""
    import heliojax as hj

    if strategy == "vmap-restart":
        return hj.Vmap(restart_after=hj.fitting.RESTART_AFTER)
    return hj.fitting.batching_from_name(strategy, chunk_size)


def time_heliojax(data, strategy, chunk_size, repeats, robust=False, linear_solver="auto"):
    """``(solution, first_call_s, best_later_s, later_calls)`` of :func:`heliojax.fit`
    (with ``robust``: the :class:`heliojax.fitting.RobustFit` of
    :func:`heliojax.fitting.fit_robust`, all its passes timed)."""
    import jax
    import jax.numpy as jnp

    import heliojax as hj

    batching = batching_of(strategy, chunk_size)
    solver = lm_solver(linear_solver)
    model = hj.StoneModel.nominal(jnp.float64)
    times = []
    result = None
    for _ in range(1 + max(1, repeats)):
        t0 = time.perf_counter()
        if robust:
            result = hj.fitting.fit_robust(model, data, batching=batching, solver=solver)
            jax.block_until_ready(result.solution.cost)
        else:
            result = hj.fit(model, data, batching=batching, solver=solver)
            jax.block_until_ready(result.cost)
        times.append(time.perf_counter() - t0)
    return result, times[0], min(times[1:]), times[1:]


def plant_gross_errors(focal, position, fraction, seed):
    """``(focal, planted)``: ``fraction`` of the records' focal spots ``(N, M, 3)``
    displaced by a beam error of 10-100 mrad in a random direction (the robust fit's
    acceptance case); ``planted`` ``(N, M)`` marks them."""
    rng = np.random.default_rng(seed + 7919)
    planted = rng.random(focal.shape[:2]) < fraction
    d = focal - position[:, None, :]
    dist = np.linalg.norm(d, axis=-1, keepdims=True)
    e = np.cross(d / dist, rng.normal(size=d.shape))
    e /= np.linalg.norm(e, axis=-1, keepdims=True)
    shifted = focal + e * dist * rng.uniform(10e-3, 100e-3, size=focal.shape[:2] + (1,))
    return np.where(planted[..., None], shifted, focal), planted


def profile_call(data, strategy, chunk_size, linear_solver, log_dir, top=25):
    """One more warm call of the fit under ``jax.profiler.trace`` (a Perfetto trace in
    ``log_dir``): the call's wall time, and per device the busy time and the ``top``
    operations (kernels on a GPU) by total duration."""
    import glob
    import gzip

    import jax
    import jax.numpy as jnp

    import heliojax as hj

    batching = batching_of(strategy, chunk_size)
    solver = lm_solver(linear_solver)
    model = hj.StoneModel.nominal(jnp.float64)
    with jax.profiler.trace(log_dir, create_perfetto_trace=True):
        t0 = time.perf_counter()
        jax.block_until_ready(hj.fit(model, data, batching=batching, solver=solver).cost)
        wall = time.perf_counter() - t0
    path = sorted(glob.glob(os.path.join(log_dir, "**", "perfetto_trace.json.gz"), recursive=True))[-1]
    with gzip.open(path) as f:
        trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    process = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    per_device = {}
    for e in events:
        name = process.get(e.get("pid"), "")
        if e.get("ph") != "X" or not ("device" in name.lower() or "gpu" in name.lower()):
            continue
        d = per_device.setdefault(name, {"busy_ms": 0.0, "events": 0, "ops": {}})
        d["busy_ms"] += e.get("dur", 0.0) / 1e3
        d["events"] += 1
        op = d["ops"].setdefault(e["name"][:120], [0.0, 0])
        op[0] += e.get("dur", 0.0) / 1e3
        op[1] += 1
    for d in per_device.values():
        ranked = sorted(d.pop("ops").items(), key=lambda kv: -kv[1][0])[:top]
        d["top_ms_count"] = [[k, round(v[0], 3), v[1]] for k, v in ranked]
    return {"wall_s": wall, "trace": path, "processes": sorted(set(process.values())), "devices": per_device}


def heldout_rms(params, geometry, context, counts, focal, mask):
    """Fleet RMS (mrad) and per-heliostat RMS of the beam pointing error over the
    held-out records, with :func:`heliojax.beam_errors_mrad`."""
    import jax
    import jax.numpy as jnp

    import heliojax as hj

    nominal = hj.StoneModel.nominal(jnp.float64)
    view = hj.ParameterView.of(nominal)
    models = jax.vmap(view.from_vector)(hj.broadcast_model(nominal, len(params)), jnp.asarray(params))
    e = np.asarray(hj.beam_errors_mrad(models, geometry, counts, context, focal, mask))
    sq = np.where(mask, e, 0.0) ** 2
    per = np.sqrt(sq.sum(1) / np.maximum(mask.sum(1), 1))
    return float(np.sqrt(sq.sum() / mask.sum())), per


# --------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------


def _machine():
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} logical cores, {platform.system()} {platform.release()}"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--heliostats", type=integer(1), default=1000)
    p.add_argument("--records", type=integer(1), default=100)
    p.add_argument("--noise", type=number(0.0), default=0.2, help="measurement noise, mrad per component")
    p.add_argument("--train-fraction", type=number(0.0, 1.0, above=True, below=True), default=0.7)
    p.add_argument(
        "--strategy",
        default="auto",
        help="auto|vmap|vmap-restart|chunked|map|threaded (map in one block per core), or a comma list to time several",
    )
    p.add_argument("--chunk-size", type=integer(1), default=64)
    p.add_argument("--profile", default=None, help="directory: profile one more warm call (JSON key 'profile')")
    p.add_argument(
        "--linear-solver",
        default="auto",
        help="LM step: auto (heliojax's default: qr on CPU, cholesky on accelerators), qr (optimistix's) or "
        "cholesky (normal equations), or a comma list to time several",
    )
    p.add_argument("--skip-other-bucket", action="store_true", help="do not time the compile of a second bucket")
    p.add_argument("--repeats", type=integer(1), default=2, help="timed calls after the compiling one")
    p.add_argument("--no-pad", action="store_true", help="fit the exact shape (no shape buckets)")
    p.add_argument("--skip-scipy", action="store_true")
    p.add_argument("--scipy-heliostats", type=integer(1), default=None, help="time scipy on this many and extrapolate")
    p.add_argument(
        "--scipy-budget", type=number(0.0), default=300.0, help="s; above the estimate, scipy is extrapolated"
    )
    p.add_argument("--seed", type=integer(0), default=0)
    p.add_argument("--json", action="store_true", help="print one JSON object only")
    p.add_argument(
        "--data",
        default=None,
        help="npz of the simulated fleet: read if it exists, else simulate and write it (default: a temporary file)",
    )
    p.add_argument("--sim-chunk", type=integer(1), default=None, help="heliostats per simulation chunk")
    p.add_argument("--skip-robust", action="store_true", help="do not time the robust fit")
    p.add_argument(
        "--gross-fraction",
        type=number(0.0, 1.0, below=True),
        default=0.0,
        help="fraction of the training records displaced by 10-100 mrad (gross errors; default none)",
    )
    p.add_argument(
        "--cli-xla-flags",
        action="store_true",
        help="compile as the heliojax command and the test suite do (XLA's older CPU fusion emitters, "
        "heliojax/_xla_flags.py, for every program); default: the library's (the same option for the fit's "
        "and its evaluation programs alone, XLA's defaults for the rest)",
    )
    p.add_argument("--simulate-to", default=None, help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.cli_xla_flags:  # before JAX starts its backend
        from heliojax._xla_flags import with_fast_cpu_compilation

        os.environ["XLA_FLAGS"] = with_fast_cpu_compilation(os.environ.get("XLA_FLAGS", ""))
    import jax

    jax.config.update("jax_enable_x64", True)
    import heliojax as hj
    from heliojax.fitting import default_batching

    log = (lambda *a: print(*a, file=sys.stderr)) if args.json else print
    n, m = args.heliostats, args.records
    chunk = args.sim_chunk or (1000 if jax.default_backend() == "cpu" else 20000)
    if args.simulate_to:  # child process: simulate and write, nothing else
        save_fleet(args.simulate_to, simulate_fleet(n, m, args.noise, args.seed, chunk))
        return 0
    # The simulation runs in a child process, so that the peak memory reported
    # below is the fits' (and the data's), not the simulator's.
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.data or os.path.join(tmp, "fleet.npz")
        if not os.path.exists(path):
            cmd = [
                sys.executable,
                os.path.abspath(__file__),
                "--simulate-to",
                path,
                "--heliostats",
                str(n),
                "--records",
                str(m),
                "--noise",
                str(args.noise),
                "--seed",
                str(args.seed),
                "--sim-chunk",
                str(chunk),
            ]
            subprocess.run(cmd, check=True, stdout=sys.stderr)
        geometry, true, context, counts, focal, hit = load_fleet(path)
    if counts.shape[:2] != (n, m):
        raise SystemExit(f"{path} holds a fleet of shape {counts.shape[:2]}, not ({n}, {m})")
    sim_s = time.perf_counter() - t0
    n_train = int(round(args.train_fraction * m))
    train_idx = np.arange(n_train)
    test_idx = np.arange(n_train, m)
    # Every record is a measurement (the spot on the target's plane), on target or not.
    train_mask = np.ones((n, n_train), bool)
    test_mask = np.ones((n, m - n_train), bool)
    log(f"simulated {n} x {m} records in {sim_s:.1f} s ({hit.mean():.3f} on target)")

    train = [_take_records(x, train_idx) for x in (context, counts, focal)]
    test = [_take_records(x, test_idx) for x in (context, counts, focal)]
    planted = np.zeros((n, n_train), bool)
    if args.gross_fraction > 0:
        train[2], planted = plant_gross_errors(
            np.asarray(train[2]), np.asarray(geometry.position), args.gross_fraction, args.seed
        )
    data = heliojax_data(geometry, *train, train_mask, pad=not args.no_pad)

    backend = jax.default_backend()
    strategies = [s.strip() for s in args.strategy.split(",")]
    default = default_batching(backend)
    if isinstance(default, (hj.LaxMap, hj.Threaded)):
        auto = "map" if isinstance(default, hj.LaxMap) else "threaded"
    else:
        auto = "vmap-restart" if default.restart_after else "vmap"
    resolved = [auto if s == "auto" else s for s in strategies]
    linear_solvers = [x.strip() for x in args.linear_solver.split(",")]
    per_strategy = {}
    best = None
    for s in resolved:
        for ls in linear_solvers:
            key = s if len(linear_solvers) == 1 else f"{s}+{ls}"
            res, first, run, later = time_heliojax(data, s, args.chunk_size, args.repeats, linear_solver=ls)
            per_strategy[key] = {"heliojax_s": run, "compile_s": first - run, "first_call_s": first, "calls_s": later}
            per_strategy[key]["lm_steps_mean"] = float(np.mean(np.asarray(res.n_steps)[:n]))
            log(f"heliojax[{key}]: first call {first:.2f} s, then {', '.join(f'{x:.2f}' for x in later)} s")
            if best is None or run < per_strategy[best[0]]["heliojax_s"]:
                best = (key, s, ls, res)
    best_key, strategy, linear_solver, res = best
    # Compile cost of one more shape bucket once the process is warm (the first
    # call above also pays one-off tracing / initialisation of JAX and optimistix).
    other = jax.tree_util.tree_map(
        lambda x: (
            np.concatenate([x, np.zeros((x.shape[0], 32) + x.shape[2:], x.dtype)], axis=1)
            if np.ndim(x) >= 2 and np.shape(x)[1] == data.mask.shape[1]
            else x
        ),
        jax.device_get(data),
    )
    compile_other = None
    if not args.skip_other_bucket:
        _, first_o, run_o, _ = time_heliojax(
            jax.device_put(other), strategy, args.chunk_size, 1, linear_solver=linear_solver
        )
        compile_other = first_o - run_o
        log(f"heliojax[{best_key}]: another shape bucket compiles in {compile_other:.2f} s")
    # the robust fit (least squares + two Cauchy passes of the same compiled program)
    if not args.skip_robust:
        res_r, first_r, run_r, later_r = time_heliojax(
            data, strategy, args.chunk_size, args.repeats, robust=True, linear_solver=linear_solver
        )
        log(f"heliojax robust[{strategy}]: first call {first_r:.2f} s, then {', '.join(f'{x:.2f}' for x in later_r)} s")
    params_hj = np.asarray(res.parameters())[:n]
    status = np.asarray(res.status)[:n]
    steps = np.asarray(res.n_steps)[:n]
    rms_hj, per_hj = heldout_rms(params_hj, geometry, test[0], test[1], test[2], test_mask)

    out = {
        "heliojax_s": per_strategy[best_key]["heliojax_s"],
        "compile_s": per_strategy[best_key]["compile_s"],
        "compile_s_warm_process_other_bucket": compile_other,
        "scipy_s": None,
        "ratio": None,
        "heldout_rms_mrad_heliojax": rms_hj,
        "heldout_rms_mrad_scipy": None,
        "peak_rss_mb": None,
        "heliostats": n,
        "records": m,
        "train_records": n_train,
        "fit_shape": list(data.counts.shape[:2]),
        "noise_mrad": args.noise,
        "gross_fraction": args.gross_fraction,
        "planted_records": int(planted.sum()),
        "strategy": strategy,
        "linear_solver": linear_solver,
        "chunk_size": args.chunk_size if strategy == "chunked" else None,
        "per_strategy": per_strategy,
        "backend": backend,
        "devices": [str(d) for d in jax.devices()],
        "machine": _machine(),
        "jax_version": jax.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "dtype": str(data.counts.dtype),
        "simulate_s": sim_s,
        "converged_fraction": float(np.mean(status == 0)),
        "lm_steps_mean": float(steps.mean()),
        "lm_steps_max": int(steps.max()),
        "lm_steps_quantiles": {q: float(np.quantile(steps, float(q))) for q in ("0.5", "0.9", "0.99", "0.999")},
    }
    if args.profile:
        out["profile"] = profile_call(data, strategy, args.chunk_size, linear_solver, args.profile)
    if not args.skip_robust:
        sol_r = res_r.solution
        rms_r, _ = heldout_rms(np.asarray(sol_r.parameters())[:n], geometry, test[0], test[1], test[2], test_mask)
        flagged = np.asarray(res_r.outlier)[:n, :n_train]
        out.update(
            robust_cauchy_heliostats=int(np.isfinite(np.asarray(res_r.scale_mrad)[:n]).sum()),
            robust_lm_steps_mean=float(np.mean(np.asarray(sol_r.n_steps)[:n])),
            planted_flagged_fraction=float(flagged[planted].mean()) if planted.any() else None,
            clean_flagged_fraction=float(flagged[~planted].mean()),
            robust_s=run_r,
            robust_first_call_s=first_r,
            robust_over_plain=run_r / out["heliojax_s"],
            heldout_rms_mrad_heliojax_robust=rms_r,
        )

    out["peak_rss_mb_before_scipy"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if not args.skip_scipy:
        import scipy

        out["scipy_version"] = scipy.__version__
        geoms = _geom_dicts(geometry)
        sun_tr, counts_tr, focal_tr = np.asarray(train[0].sun), np.asarray(train[1]), np.asarray(train[2])
        k = args.scipy_heliostats
        if k is None:
            probe = min(n, 20)
            _, _, probe_s = scipy_fit_fleet(geoms, counts_tr, sun_tr, focal_tr, train_mask, probe)
            estimate = probe_s / probe * n
            k = n if estimate <= args.scipy_budget else max(probe, int(args.scipy_budget / (probe_s / probe)))
            log(f"scipy probe: {probe_s / probe * 1e3:.1f} ms per heliostat, estimate {estimate:.0f} s")
        k = min(k, n)
        params_sp, nfev, scipy_k_s = scipy_fit_fleet(geoms, counts_tr, sun_tr, focal_tr, train_mask, k)
        scipy_s = scipy_k_s * n / k
        sub = np.arange(k)
        rms_sp, per_sp = heldout_rms(params_sp, *_sub((geometry, test[0], test[1], test[2], test_mask), sub))
        rms_hj_sub = float(np.sqrt(np.sum(per_hj[sub] ** 2 * test_mask[sub].sum(1)) / test_mask[sub].sum()))
        log(f"scipy: {scipy_k_s:.2f} s for {k} heliostats")
        out.update(
            scipy_s=scipy_s,
            ratio=scipy_s / out["heliojax_s"],
            ratio_robust=scipy_s / out["robust_s"] if "robust_s" in out else None,
            heldout_rms_mrad_scipy=rms_sp,
            heldout_rms_mrad_heliojax_same_heliostats=rms_hj_sub,
            heldout_rms_abs_diff_mrad=abs(rms_sp - rms_hj_sub),
            heldout_per_heliostat_max_abs_diff_mrad=float(np.max(np.abs(per_sp - per_hj[sub]))),
            params_max_abs_diff=float(np.max(np.abs(params_sp - params_hj[sub]))),
            scipy_measured_heliostats=k,
            scipy_extrapolated=k < n,
            scipy_nfev_mean=float(nfev.mean()),
            scipy_jacobian="2-point finite differences (scipy default)",
        )
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if args.json:
        print(json.dumps(out))
    else:
        print(json.dumps(out, indent=2))
    return 0


def _sub(trees, idx):
    import jax

    return jax.tree.map(lambda x: np.asarray(x)[idx], trees)


if __name__ == "__main__":
    sys.exit(main())
