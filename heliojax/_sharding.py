"""Fleet calibration beyond one device: sharding over local devices, and multi-host.

Local devices
-------------
:func:`fit_fleet_sharded` splits the heliostat axis over all local devices (or the
given ones): a one-axis :class:`jax.sharding.Mesh` named ``"heliostats"``. The
fleet is padded to a multiple ``D * k`` of the device count with copies of
heliostat 0 whose mask is all False (status ``padding``), reshaped to
``(D, k, ...)`` and placed with ``NamedSharding(mesh, P("heliostats"))``, so
device ``d`` holds heliostats ``d k .. (d+1) k - 1``. One compiled program maps
over the device axis with ``jax.vmap``; inside, each device batches its ``k``
heliostats exactly as :func:`heliojax.fit_fleet` does (the strategy of
:func:`heliojax.default_strategy` for the devices' platform: ``lax.map`` on CPU,
``vmap`` on GPU/TPU, or ``config.strategy``). XLA's SPMD partitioner splits the
device axis, so each device computes only its own block; the only communication
is the all-reduce of the solver loop's "any lane still running" flag, which keeps
the devices' LM loops in step (each device's loop runs until the slowest of the
``D`` heliostats at that position converges). Padding is stripped from the
result. Heliostats are independent problems, so the result equals single-device
:func:`heliojax.fit_fleet` (to 1e-12 in the tests, in practice to the last bit
or within 1 ulp).

Why not ``jax.shard_map`` (or ``jax.pmap``, which JAX 0.10 implements with it):
lineax (0.1.1, used by optimistix's LM) fails inside it. With
``check_vma=False`` the linear solve raises ``ValueError: pytree does not match
out_structure`` (lineax compares ``ShapeDtypeStruct`` objects, and inside shard_map
one of them carries the manual-axis sharding: lineax issue #185, open); with
``check_vma=True`` JAX raises ``ValueError: Primitive dot_general requires
varying manual axes to match, but got [frozenset(), frozenset({'heliostats'})]``
(and ``scatter_add`` likewise) from optimistix's autodiff. The ``vmap`` over a
sharded device axis gives the same per-device programs without either.

On one CPU the devices are simulated with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (set before JAX is imported;
the tests run it in a subprocess).

Multi-host
----------
Each process (one per host, or several per host) calls
``jax.distributed.initialize(coordinator_address, num_processes, process_id)``,
loads only its own heliostats, ``process_slice(n_heliostats)`` of the fleet's
order, fits them on its local devices, and the results are gathered with
:func:`jax.experimental.multihost_utils.process_allgather` so that every process
ends with the full :class:`~heliojax.FitResult` (heliostats in fleet order).
:func:`calibrate_distributed` does all of it::

    import jax
    jax.config.update("jax_enable_x64", True)
    jax.distributed.initialize("10.0.0.1:4321", num_processes=4, process_id=RANK)

    def load(sl: slice) -> heliojax.CalibrationData:
        fleet = heliojax.load_paint_directory(DATA, heliostats=ALL_IDS[sl])  # only these
        return heliojax.CalibrationData.from_fleet(heliojax.pad_fleet(fleet, n_records=M))

    result = heliojax.calibrate_distributed(load, n_heliostats=len(ALL_IDS))
    # every process now holds all len(ALL_IDS) heliostats' parameters

(Every process must pad its records to the same ``M``: the gathered arrays are
concatenated along the heliostat axis.) Only the final gather communicates: the
fits themselves are independent, so a slow network costs nothing during the
solve. On CPU the cross-process gather uses JAX's CPU collectives (gloo over TCP,
the default of ``jax_cpu_collectives_implementation`` in JAX 0.10); the test
runs two processes on 127.0.0.1.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Float

from ._calibration import (
    CalibrationData,
    FitConfig,
    FitResult,
    ModelSpec,
    _batched,
    _fit_one,
    default_strategy,
    model_spec,
)

AXIS = "heliostats"
"""Name of the mesh axis the heliostats are sharded over."""


def _pad_heliostats(tree, n: int):
    """Append ``n`` copies of heliostat 0 to every leaf (numpy for concrete
    arrays: no compilation per shape)."""
    if n == 0:
        return tree

    def grow(x):
        xp = jnp if isinstance(x, jax.core.Tracer) else np
        x = xp.asarray(x)
        return xp.concatenate([x, xp.repeat(x[:1], n, axis=0)], axis=0)

    return jax.tree.map(grow, tree)


def _resolve(spec, config, devices):
    if isinstance(spec, str):
        spec = model_spec(spec)
    devices = list(jax.local_devices() if devices is None else devices)
    if not devices:
        raise ValueError("no devices to shard over")
    platforms = {d.platform for d in devices}
    if len(platforms) != 1:
        raise ValueError(f"devices of one platform expected, got {sorted(platforms)}")
    strategy = config.strategy if config.strategy != "auto" else default_strategy(platforms.pop())
    return spec, devices, strategy


@eqx.filter_jit
def _fit_sharded_compiled(spec, config, strategy, base, data: CalibrationData):
    """``base`` and ``data`` have a leading device axis ``(D, H / D, ...)`` sharded
    over the mesh; each device batches its ``H / D`` heliostats by ``strategy``."""
    fn = lambda b, g, c, s, f, m: _fit_one(spec, config, b, g, c, s, f, m)  # noqa: E731
    batched = _batched(fn, strategy, config.chunk_size)

    def per_device(b, d):
        return batched(b, d.geometry, d.counts, d.context, d.focal_spot, d.mask)

    return jax.vmap(per_device)(base, data)


def fit_fleet_sharded(
    data: CalibrationData,
    spec: ModelSpec | str = "stone8",
    config: FitConfig = FitConfig(),
    initial: Float[Array, "H P"] | None = None,
    devices: Sequence[jax.Device] | None = None,
) -> FitResult:
    """:func:`heliojax.fit_fleet` with the heliostat axis sharded over devices.

    Args:
        data: batched arrays ``(H, M, ...)`` (any ``H``: padded here to a multiple of
            the device count; pad records to a shape bucket as for ``fit_fleet``).
        spec: a :class:`ModelSpec` or ``"stone8"`` / ``"actuator"``.
        config: solver settings; ``strategy="auto"`` picks the strategy of the
            devices' platform (``lax.map`` on CPU, ``vmap`` on accelerators) for
            the heliostats inside each device's shard.
        initial: ``(H, P)`` physical start values (default: nominal).
        devices: devices to shard over (default: all local devices, ``jax.local_devices()``).

    Returns:
        A :class:`FitResult` over the ``H`` heliostats (padding stripped), equal to
        the single-device ``fit_fleet`` result (arrays on the mesh's devices;
        ``np.asarray`` gathers them).
    """
    spec, devices, strategy = _resolve(spec, config, devices)
    h = data.counts.shape[0]
    dtype = data.counts.dtype
    if initial is None:
        initial = np.broadcast_to(np.asarray(spec.nominal, dtype), (h, len(spec.names)))
    n_dev = len(devices)
    h_pad = max(n_dev, math.ceil(h / n_dev) * n_dev)
    extra = h_pad - h
    if extra:
        data = _pad_heliostats(data, extra)
        data = eqx.tree_at(lambda d: d.mask, data, _mask_tail(data.mask, h))
        initial = _pad_heliostats(initial, extra)
    per = h_pad // n_dev
    split = lambda x: x.reshape((n_dev, per) + x.shape[1:])  # noqa: E731
    sharding = NamedSharding(Mesh(np.asarray(devices), (AXIS,)), P(AXIS))
    data = jax.device_put(jax.tree.map(lambda x: split(np.asarray(x)), data), sharding)
    base = jax.device_put(split(np.asarray(initial, dtype)), sharding)
    out = _fit_sharded_compiled(spec, config, strategy, base, data)
    out = {k: v.reshape((h_pad,) + v.shape[2:])[:h] for k, v in out.items()}
    return FitResult(spec=spec, **out)


def _mask_tail(mask, h):
    xp = jnp if isinstance(mask, jax.core.Tracer) else np
    mask = xp.asarray(mask)
    keep = (xp.arange(mask.shape[0]) < h)[:, None]
    return mask & keep


# --------------------------------------------------------------------------------------
# Multi-host
# --------------------------------------------------------------------------------------


def process_slice(
    n_heliostats: int, process_index: int | None = None, process_count: int | None = None
) -> slice:
    """The contiguous block of heliostats (in fleet order) that process
    ``process_index`` of ``process_count`` handles: sizes differ by at most one,
    the first ``n_heliostats % process_count`` processes take one more.

    Defaults: ``jax.process_index()`` and ``jax.process_count()``.
    """
    i = jax.process_index() if process_index is None else int(process_index)
    p = jax.process_count() if process_count is None else int(process_count)
    n = int(n_heliostats)
    if p < 1 or not 0 <= i < p:
        raise ValueError(f"process_index {i} outside 0..{p - 1}")
    if n < 0:
        raise ValueError(f"n_heliostats must be >= 0, got {n}")
    q, r = divmod(n, p)
    start = i * q + min(i, r)
    return slice(start, start + q + (1 if i < r else 0))


def gather_results(local: FitResult, n_heliostats: int) -> FitResult:
    """Gather every process's :class:`FitResult` of its :func:`process_slice` into
    the full fleet's result (fleet order), on every process.

    Each process pads its block to the largest block size, the blocks are
    all-gathered (:func:`jax.experimental.multihost_utils.process_allgather`) and
    the padding is removed. A collective: every process must call it.
    """
    from jax.experimental import multihost_utils

    p = jax.process_count()
    sizes = [process_slice(n_heliostats, i, p).stop - process_slice(n_heliostats, i, p).start for i in range(p)]
    mine = sizes[jax.process_index()]
    h_local = local.status.shape[0]
    if h_local != mine:
        raise ValueError(
            f"process {jax.process_index()} holds {h_local} heliostats, its process_slice has {mine}"
        )
    width = max(sizes) if sizes else 0
    arrays = {k: np.asarray(getattr(local, k)) for k in _RESULT_FIELDS}
    padded = {k: _pad_rows(v, width) for k, v in arrays.items()}
    if p == 1:
        gathered = {k: v[None] for k, v in padded.items()}
    else:
        gathered = multihost_utils.process_allgather(padded, tiled=False)
    out = {
        k: np.concatenate([np.asarray(v)[i, : sizes[i]] for i in range(p)], axis=0) for k, v in gathered.items()
    }
    return FitResult(spec=local.spec, **{k: jnp.asarray(v) for k, v in out.items()})


_RESULT_FIELDS = ("params", "std", "status", "n_steps", "n_used", "rms_mrad", "final_cost")


def _pad_rows(x: np.ndarray, width: int) -> np.ndarray:
    if x.shape[0] >= width:
        return x
    fill = np.zeros((width - x.shape[0],) + x.shape[1:], x.dtype)
    return np.concatenate([x, fill], axis=0)


def calibrate_distributed(
    load_slice: Callable[[slice], CalibrationData],
    n_heliostats: int,
    spec: ModelSpec | str = "stone8",
    config: FitConfig = FitConfig(),
    initial: Callable[[slice], Float[Array, "h P"]] | None = None,
) -> FitResult:
    """Multi-host fleet calibration: this process loads and fits its own
    :func:`process_slice` of the heliostats, then all processes exchange results.

    Call ``jax.distributed.initialize(...)`` first (and enable float64); every
    process calls this function with the same ``n_heliostats``, ``spec`` and
    ``config``. With one process it is :func:`fit_fleet_sharded` on the local
    devices.

    Args:
        load_slice: ``load_slice(slice) -> CalibrationData`` of exactly the
            heliostats ``slice`` (fleet order); every process's data must have the
            same record count ``M``.
        n_heliostats: fleet size ``H``.
        spec, config: as for :func:`heliojax.fit_fleet`.
        initial: optional ``initial(slice) -> (h, P)`` start values.

    Returns:
        The full fleet's :class:`FitResult` (``H`` heliostats), on every process.
    """
    sl = process_slice(n_heliostats)
    data = load_slice(sl)
    n_local = sl.stop - sl.start
    if data.counts.shape[0] != n_local:
        raise ValueError(f"load_slice({sl}) returned {data.counts.shape[0]} heliostats, expected {n_local}")
    init = None if initial is None else initial(sl)
    if n_local:
        local = fit_fleet_sharded(data, spec, config, init, devices=jax.local_devices())
    else:
        local = _empty_result(spec, data.counts.dtype)
    return gather_results(local, n_heliostats)


def _empty_result(spec, dtype) -> FitResult:
    if isinstance(spec, str):
        spec = model_spec(spec)
    k = len(spec.names)
    return FitResult(
        params=jnp.zeros((0, k), dtype),
        std=jnp.zeros((0, k), dtype),
        status=jnp.zeros((0,), jnp.int32),
        n_steps=jnp.zeros((0,), jnp.int32),
        n_used=jnp.zeros((0,), jnp.int32),
        rms_mrad=jnp.zeros((0,), dtype),
        final_cost=jnp.zeros((0,), dtype),
        spec=spec,
    )


__all__ = [
    "AXIS",
    "calibrate_distributed",
    "fit_fleet_sharded",
    "gather_results",
    "process_slice",
]

