"""Fleet calibration beyond one device: sharding over local devices, and multi-host.

Local devices
-------------
:class:`heliojax.fitting.Sharded` batching splits the heliostat axis over all local devices (or the
given ones): a one-axis :class:`jax.sharding.Mesh` named ``"heliostats"``. The
fleet is padded to a multiple ``D * k`` of the device count with copies of
heliostat 0 whose mask is all False (status ``padding``), reshaped to
``(D, k, ...)`` and placed with ``NamedSharding(mesh, P("heliostats"))``, so
device ``d`` holds heliostats ``d k .. (d+1) k - 1``. One compiled program maps
over the device axis with ``jax.vmap``; inside, each device batches its ``k``
heliostats exactly as `heliojax.fitting` does (the strategy of
:func:`heliojax.default_strategy` for the devices' platform: ``lax.map`` on CPU,
``vmap`` on GPU/TPU, or ``config.strategy``). XLA's SPMD partitioner splits the
device axis, so each device computes only its own block; the only communication
is the all-reduce of the solver loop's "any lane still running" flag, which keeps
the devices' LM loops in step (each device's loop runs until the slowest of the
``D`` heliostats at that position converges). Padding is stripped from the
result. Heliostats are independent problems, so the result equals single-device
`heliojax.fitting` (to 1e-12 in the tests, in practice to the last bit
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

    def load(sl: slice) -> heliojax.Fleet:
        fleet = heliojax.load_paint_directory(DATA, heliostats=ALL_IDS[sl])  # only these
        return heliojax.pad_fleet(fleet, n_records=M)

    result = heliojax.calibrate_distributed(load, heliojax.ActuatorModel.nominal(), n_heliostats=len(ALL_IDS))
    # every process now holds all len(ALL_IDS) heliostats' parameters

(Every process must pad its records to the same ``M``: the gathered arrays are
concatenated along the heliostat axis.) Only the final gather communicates: the
fits themselves are independent, so a slow network costs nothing during the
solve. On CPU the cross-process gather uses JAX's CPU collectives (gloo over TCP,
the default of ``jax_cpu_collectives_implementation`` in JAX 0.10); the test
runs two processes on 127.0.0.1.
"""

from __future__ import annotations

import typing
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils

from .._kinematics import AbstractKinematicModel
from .._limits import count_problem
from ._batching import MAX_COUNT, Sharded
from ._fit import FitSolution, fit


def process_slice(n_heliostats: int, process_index: int | None = None, process_count: int | None = None) -> slice:
    """The contiguous block of heliostats (in fleet order) that process
    ``process_index`` of ``process_count`` handles: sizes differ by at most one,
    the first ``n_heliostats % process_count`` processes take one more.

    Defaults: ``jax.process_index()`` and ``jax.process_count()``.

    Raises:
        ValueError: an argument that is no whole number in its range (2.5 heliostats
            had been read as 2, ``True`` as 1), or ``process_index`` outside
            ``0..process_count - 1``.
    """
    for name, value, minimum in (
        ("n_heliostats", n_heliostats, 0),
        ("process_index", process_index, 0),
        ("process_count", process_count, 1),
    ):
        problem = None if value is None else count_problem(value, MAX_COUNT, minimum=minimum)
        if problem is not None:
            raise ValueError(f"process_slice: {name} {problem}")
    i = jax.process_index() if process_index is None else int(process_index)
    p = jax.process_count() if process_count is None else int(process_count)
    n = int(n_heliostats)
    if not 0 <= i < p:
        raise ValueError(f"process_index {i} outside 0..{p - 1}")
    q, r = divmod(n, p)
    start = i * q + min(i, r)
    return slice(start, start + q + (1 if i < r else 0))


def _pad_rows(x: np.ndarray, width: int) -> np.ndarray:
    if x.shape[0] >= width:
        return x
    fill = np.zeros((width - x.shape[0],) + x.shape[1:], x.dtype)
    return np.concatenate([x, fill], axis=0)


def gather_solutions(local: FitSolution, n_heliostats: int) -> FitSolution:
    """Gather every process's :class:`FitSolution` of its :func:`process_slice` into
    the full fleet's solution (fleet order), on every process.

    Each process pads its block to the largest block size, the blocks are
    all-gathered (:func:`jax.experimental.multihost_utils.process_allgather`) and
    the padding is removed. A collective: every process must call it.
    """
    p = jax.process_count()
    slices = [process_slice(n_heliostats, i, p) for i in range(p)]
    sizes = [s.stop - s.start for s in slices]
    mine = sizes[jax.process_index()]
    if local.n_heliostats != mine:
        raise ValueError(
            f"process {jax.process_index()} holds {local.n_heliostats} heliostats, its process_slice has {mine}"
        )
    width = max(sizes) if sizes else 0
    leaves, treedef = jax.tree.flatten(local)
    padded = [_pad_rows(np.asarray(v), width) for v in leaves]
    if p == 1:
        gathered = [v[None] for v in padded]
    else:
        gathered = multihost_utils.process_allgather(padded, tiled=False)
    out = [jnp.asarray(np.concatenate([np.asarray(v)[i, : sizes[i]] for i in range(p)], axis=0)) for v in gathered]
    return jax.tree.unflatten(treedef, out)


def calibrate_distributed(
    load_slice: Callable[[slice], typing.Any],
    model0: AbstractKinematicModel,
    n_heliostats: int,
    **fit_options: typing.Any,
) -> FitSolution:
    """Multi-host fleet calibration: this process loads and fits its own
    :func:`process_slice` of the heliostats, then all processes exchange results.

    Call ``jax.distributed.initialize(...)`` first (and enable float64); every
    process calls this function with the same ``n_heliostats``, ``model0`` and
    options. With one process it is :func:`heliojax.fit` sharded over the local devices.

    Args:
        load_slice: ``load_slice(slice) -> Fleet`` of exactly the heliostats
            ``slice`` (fleet order); every process must pad to the same record count ``M``.
        model0: the start model (one model for every heliostat).
        n_heliostats: fleet size ``H``.
        fit_options: keyword arguments of :func:`heliojax.fit` (not ``batching``).

    Returns:
        The full fleet's :class:`FitSolution` (``H`` heliostats), on every process.
    """
    sl = process_slice(n_heliostats)
    fleet = load_slice(sl)
    n_local = sl.stop - sl.start
    if int(np.shape(fleet.mask)[0]) != n_local:
        raise ValueError(f"load_slice({sl}) returned {np.shape(fleet.mask)[0]} heliostats, expected {n_local}")
    batching = Sharded(devices=tuple(jax.local_devices())) if n_local else None
    local = fit(model0, fleet, batching=batching, **fit_options)
    return gather_solutions(local, n_heliostats)


__all__ = ["calibrate_distributed", "gather_solutions", "process_slice"]
