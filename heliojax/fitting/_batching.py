"""How the heliostat axis of a fit is batched: small frozen strategy objects.

Every strategy maps a per-heliostat function over the leading axis of its
arguments inside one compiled program:

* :class:`Vmap` - ``jax.vmap``: wide batches, for GPUs (a batched while loop runs
  every lane until the slowest converges).
* :class:`LaxMap` - ``jax.lax.map``: lanes one after another, best on CPU.
* :class:`Chunked` - ``lax.map`` over chunks of ``size`` lanes that are vmapped.
* :class:`Sharded` - the heliostat axis split over devices (see
  :mod:`heliojax.fitting._sharding`), each device batching its block by ``inner``.
* :class:`Threaded` - the heliostat axis split into blocks, one per CPU core, each
  block's program (batched by ``inner``) run from a host thread of its own.

:func:`default_batching` is the one place where a backend picks a strategy.
"""

from __future__ import annotations

import abc
import concurrent.futures
import math
import os
import threading
import typing
from collections.abc import Callable, Iterable, Sequence

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from .._limits import count_problem

AXIS = "heliostats"
"""Name of the mesh axis the heliostats are sharded over."""

MAX_COUNT = 2**31 - 1
"""Largest count a strategy takes (steps, lanes, blocks): XLA's 32-bit loop counters."""


class AbstractBatching(eqx.Module):
    """A batching strategy over the heliostat axis."""

    @abc.abstractmethod
    def map(self, fn: Callable[..., typing.Any]) -> Callable[..., typing.Any]:
        """``fn`` (one heliostat) mapped over the leading axis of every argument."""

    def prepare(self, args: tuple[typing.Any, ...]) -> tuple[typing.Any, ...]:
        """Outside the compiled program: place or reshape the batched arguments."""
        return args

    def finish(self, out: typing.Any, n: int) -> typing.Any:
        """Outside the compiled program: undo :meth:`prepare` on the outputs (``n``
        heliostats)."""
        del n
        return out

    @property
    def skips_inactive(self) -> bool:
        """Whether a lane whose branch ``jax.lax.cond`` does not take costs nothing
        (sequential lanes); in a vmapped batch both branches are computed and selected."""
        return False

    def block(self, lanes: tuple[typing.Any, ...]) -> tuple[typing.Any, ...]:
        """Outside the compiled program: the arguments one call of the program gets
        from ``lanes`` (every leaf batched along axis 0), e.g. to compile it ahead of
        :meth:`run`. All of them, except under :class:`Threaded`."""
        return lanes

    def run(self, program: Callable[..., typing.Any], head: tuple[typing.Any, ...], lanes: tuple[typing.Any, ...]):
        """Outside the compiled program: ``program(*head, *lanes)``, ``lanes`` batched
        along axis 0 (every leaf) and ``head`` the rest. One call, except under
        :class:`Threaded`."""
        return program(*head, *lanes)

    def n_blocks(self, n: int) -> int:
        """Blocks a caller that keeps its own blocks of lanes (discovery's lane groups)
        cuts ``n`` lanes into, to run them by :meth:`each`. One, except under
        :class:`Threaded`."""
        del n
        return 1

    def each(self, work: Callable[[int], typing.Any], n: int) -> list[typing.Any]:
        """Outside the compiled programs: ``[work(k) for k in range(n)]``, ``work`` calling
        compiled programs on independent blocks of lanes. In turn, except under
        :class:`Threaded`."""
        return [work(k) for k in range(n)]


@typing.final
class Vmap(AbstractBatching):
    """``jax.vmap`` over heliostats (accelerators).

    A vmapped while loop runs every lane until the slowest has converged: on a fleet
    of 100,000 most heliostats converge in 5-6 Levenberg-Marquardt steps, a few take
    30. With ``restart_after`` set, :func:`heliojax.fit` stops every lane after that
    many steps and fits the lanes that had not converged again, from where they
    stopped, in a batch of their own (padded to a power of two) with the remaining
    steps. The restarted solver forgets its damping, so their parameters agree with a
    single run to the solver's tolerance, not bit for bit.

    Attributes:
        restart_after: steps of the first pass (``None``: one pass).
    """

    restart_after: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        # 2.5 had reached optimistix ("max_steps must be a Python integer"), "3" a comparison
        problem = None if self.restart_after is None else count_problem(self.restart_after, MAX_COUNT)
        if problem is not None:
            raise ValueError(f"Vmap: restart_after {problem} (or None: one pass)")

    def map(self, fn):
        return jax.vmap(fn)


@typing.final
class LaxMap(AbstractBatching):
    """``jax.lax.map`` over heliostats (sequential lanes; CPU)."""

    def map(self, fn):
        return lambda *xs: jax.lax.map(lambda a: fn(*a), xs)

    @property
    def skips_inactive(self) -> bool:
        return True


@typing.final
class Chunked(AbstractBatching):
    """``lax.map`` over chunks of ``size`` vmapped heliostats."""

    size: int = eqx.field(static=True, default=64)

    def __check_init__(self):
        problem = count_problem(self.size, MAX_COUNT)  # 2.5 had failed deep inside lax.map
        if problem is not None:
            raise ValueError(f"Chunked: size {problem}")

    def map(self, fn):
        return lambda *xs: jax.lax.map(lambda a: fn(*a), xs, batch_size=self.size)


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def block_lanes(n: int, n_blocks: int, size: int | None = None) -> list[np.ndarray]:
    """The lanes of each of ``n_blocks`` blocks of ``n`` lanes: lane ``i`` in block
    ``i mod n_blocks`` (a subset of active lanes, such as discovery's first fold, is
    shared out evenly), each padded to ``size`` lanes (default ``ceil(n / n_blocks)``)
    with copies of lane 0, whose results the caller strips. The one rule of
    :class:`Threaded` and of discovery's lane blocks."""
    size = -(-n // n_blocks) if size is None else size
    blocks = [np.arange(k, n, n_blocks) for k in range(n_blocks)]
    return [np.concatenate([b, np.zeros(size - b.size, int)]) for b in blocks]


_BLOCK_THREAD = "heliojax-block"
_POOLS: dict[int, concurrent.futures.ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _pool(workers: int) -> concurrent.futures.ThreadPoolExecutor:
    """The process's pool of ``workers`` block threads (made on first use: starting
    threads for every call cost ~5 % of a discovery run)."""
    with _POOLS_LOCK:
        if workers not in _POOLS:
            _POOLS[workers] = concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix=_BLOCK_THREAD)
        return _POOLS[workers]


MIN_BLOCK = 8
"""Fewest lanes a :class:`Threaded` block holds: handing a block to a thread and
copying its arrays cost ~0.1 ms, one lane's Levenberg-Marquardt fit 0.1-1 ms, so
a block of 8 lanes is at least ~8x its overhead."""


@typing.final
class Threaded(AbstractBatching):
    """The lanes split into ``workers`` blocks, each batched by ``inner`` (one compiled
    program of the block's shape) and run from a host thread of its own.

    XLA's CPU client runs a program on the thread that calls it and releases the
    GIL meanwhile, and a ``lax.map`` over lanes keeps one core busy: on a CPU of
    ``n`` cores, ``n`` blocks of lanes run at once (two programs on two threads took
    the time of one; two calls from one thread took twice that). Lane ``i`` goes to
    block ``i mod B`` (``B`` blocks), so that a subset of active lanes, such as the
    first fold of discovery's lanes, is shared out evenly; the last block is padded
    with copies of lane 0, which are stripped again. Every lane computes what one
    call of ``inner`` computes for it (bit for bit under :class:`LaxMap`, tested).
    Fewer blocks are made when a block would hold fewer than ``min_block`` lanes
    (one block: a plain call, no thread).

    Multi-device sharding (:class:`Sharded`) keeps the devices' solver loops in step
    (an all-reduce of "any lane still running" per step) and was slower on two CPU
    devices than one; blocks of independent programs share nothing.

    Attributes:
        inner: the strategy within a block (default :class:`LaxMap`).
        workers: blocks, and threads (default: the usable CPU cores).
        min_block: fewest lanes per block (default :data:`MIN_BLOCK`).
    """

    inner: AbstractBatching = eqx.field(static=True, default_factory=lambda: LaxMap())
    workers: int = eqx.field(static=True, default_factory=usable_cores)
    min_block: int = eqx.field(static=True, default=MIN_BLOCK)

    def __check_init__(self):
        for name in ("workers", "min_block"):  # 2.5 workers had failed in NumPy's arange
            problem = count_problem(getattr(self, name), MAX_COUNT)
            if problem is not None:
                raise ValueError(f"Threaded: {name} {problem}")
        if not isinstance(self.inner, AbstractBatching):  # None or "vmap" had been an AttributeError in the fit
            raise TypeError(f"Threaded: inner must be a batching strategy (e.g. LaxMap()), got {self.inner!r}"[:200])
        if isinstance(self.inner, (Threaded, Sharded)):
            raise ValueError(f"Threaded: inner must batch one block on one device, got {type(self.inner).__name__}")

    def map(self, fn):
        return self.inner.map(fn)

    @property
    def skips_inactive(self) -> bool:
        return self.inner.skips_inactive

    def n_blocks(self, n: int) -> int:
        """Blocks for ``n`` lanes: ``workers``, fewer where a block would hold fewer
        than ``min_block`` lanes."""
        return max(1, min(self.workers, n // self.min_block))

    def each(self, work, n):
        if n <= 1 or self.workers == 1:
            return [work(k) for k in range(n)]
        return self._threads(work, range(n))

    def _threads(self, work: Callable[[typing.Any], typing.Any], items: Iterable[typing.Any]) -> list:
        """``[work(x) for x in items]`` on ``workers`` host threads, each result ready
        (its programs run on the thread that called them)."""
        x64 = bool(jax.config.jax_enable_x64)  # pyright: ignore[reportAttributeAccessIssue]

        def one(item):
            with jax.enable_x64(x64):  # the caller's setting (a context is per thread)
                return jax.block_until_ready(work(item))

        if threading.current_thread().name.startswith(_BLOCK_THREAD):  # within a block: no thread waits for its pool
            return [one(x) for x in items]
        return list(_pool(self.workers).map(one, items))

    def _blocks(self, lanes: tuple[typing.Any, ...]) -> list[tuple[typing.Any, ...]]:
        n = int(jax.tree.leaves(lanes)[0].shape[0])
        b = self.n_blocks(n)
        if b == 1:
            return [lanes]
        host = jax.tree.map(np.asarray, lanes)  # numpy: no XLA program per gather
        return [jax.tree.map(lambda x, i=i: x[i], host) for i in block_lanes(n, b)]

    def block(self, lanes):
        return self._blocks(lanes)[0]

    def run(self, program, head, lanes):
        blocks = self._blocks(lanes)
        if len(blocks) == 1:
            return program(*head, *lanes)
        n = int(jax.tree.leaves(lanes)[0].shape[0])
        outs = self._threads(lambda block: program(*head, *block), blocks)

        def interleave(*parts):
            if not eqx.is_array(parts[0]):
                return parts[0]
            stacked = np.stack([np.asarray(p) for p in parts], axis=1)  # (size, B, ...): lane k*B + j
            return jax.device_put(stacked.reshape((-1,) + stacked.shape[2:])[:n])

        return jax.tree.map(interleave, *outs)


RESTART_AFTER = 12
"""First-pass steps of the default :class:`Vmap`: about twice the median number of
steps (5) of simulated fleets; at 100,000 x 100 records the 99th percentile was 16
steps and the slowest lane 35, so 1-2 % of the lanes go on to the second pass."""


def default_batching(backend: str | None = None) -> AbstractBatching:
    """On CPU, :class:`LaxMap` (sequential lanes beat vmap's lock-step while loop
    there), in one :class:`Threaded` block per usable core where there are several;
    :class:`Vmap` on accelerators, restarting the lanes that have not converged
    after :data:`RESTART_AFTER` steps."""
    backend = backend or jax.default_backend()
    if backend != "cpu":
        return Vmap(restart_after=RESTART_AFTER)
    cores = usable_cores()
    return Threaded(LaxMap(), workers=cores) if cores > 1 else LaxMap()


BATCHING_NAMES = ("auto", "vmap", "chunked", "map", "threaded")


def batching_from_name(name: str, chunk_size: int = 64) -> AbstractBatching:
    """The strategy called ``name`` (``"auto" | "vmap" | "chunked" | "map" |
    "threaded"``), as the CLI and configs name them."""
    if name == "auto":
        return default_batching()
    if name == "vmap":
        return Vmap()
    if name == "map":
        return LaxMap()
    if name == "chunked":
        return Chunked(chunk_size)
    if name == "threaded":
        return Threaded(LaxMap())
    raise ValueError(f"batching must be one of {BATCHING_NAMES}, got {name!r}")


def _pad_heliostats(tree: typing.Any, n: int) -> typing.Any:
    """Append ``n`` copies of heliostat 0 to every array leaf (numpy: no compilation
    per shape)."""
    if n == 0:
        return tree

    def grow(x):
        x = np.asarray(x)
        return np.concatenate([x, np.repeat(x[:1], n, axis=0)], axis=0)

    return jax.tree.map(grow, tree)


@typing.final
class Sharded(AbstractBatching):
    """The heliostat axis split over devices: padded to a multiple ``D k`` of the
    device count (copies of heliostat 0, stripped again), reshaped to ``(D, k, ...)``
    and placed with ``NamedSharding(mesh, P("heliostats"))``; one program maps over
    the device axis with ``vmap`` and each device batches its ``k`` heliostats by
    ``inner``.

    Attributes:
        devices: devices to shard over (default: all local devices).
        inner: the per-device strategy (default: :func:`default_batching` of the
            devices' platform).
    """

    devices: tuple[typing.Any, ...] | None = eqx.field(static=True, default=None)
    inner: AbstractBatching | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        # "cpu" for the devices had been an AttributeError, Sharded(inner=Sharded()) an
        # IndexError, None or "vmap" for the inner an AttributeError, all inside the fit
        if self.devices is not None and (
            isinstance(self.devices, (str, bytes)) or not all(hasattr(d, "platform") for d in self.devices)
        ):
            raise TypeError(
                f"Sharded: devices must be JAX devices (e.g. jax.local_devices()), got {self.devices!r}"[:200]
            )
        if self.inner is not None and not isinstance(self.inner, AbstractBatching):
            raise TypeError(
                f"Sharded: inner must be a batching strategy (e.g. LaxMap()) or None, got {self.inner!r}"[:200]
            )
        if isinstance(self.inner, (Sharded, Threaded)):
            raise ValueError(f"Sharded: inner must batch one device's heliostats, got {type(self.inner).__name__}")

    def _devices(self) -> list[typing.Any]:
        devices = list(jax.local_devices() if self.devices is None else self.devices)
        if not devices:
            raise ValueError("Sharded: no devices to shard over")
        platforms = {d.platform for d in devices}
        if len(platforms) != 1:
            raise ValueError(f"Sharded: devices of one platform expected, got {sorted(platforms)}")
        return devices

    def _inner(self) -> AbstractBatching:
        return self.inner if self.inner is not None else default_batching(self._devices()[0].platform)

    def map(self, fn):
        return jax.vmap(self._inner().map(fn))

    def prepare(self, args):
        devices = self._devices()
        n_dev = len(devices)
        h = jax.tree.leaves(args)[0].shape[0]
        h_pad = max(n_dev, math.ceil(h / n_dev) * n_dev)
        args = _pad_heliostats(args, h_pad - h)
        per = h_pad // n_dev
        sharding = NamedSharding(Mesh(np.asarray(devices), (AXIS,)), P(AXIS))
        split = lambda x: np.asarray(x).reshape((n_dev, per) + np.shape(x)[1:])  # noqa: E731
        return jax.device_put(jax.tree.map(split, args), sharding)

    def finish(self, out, n):
        return jax.tree.map(lambda v: v.reshape((-1,) + v.shape[2:])[:n], out)


__all__: Sequence[str] = (
    "AXIS",
    "BATCHING_NAMES",
    "RESTART_AFTER",
    "AbstractBatching",
    "Chunked",
    "LaxMap",
    "MIN_BLOCK",
    "Sharded",
    "Threaded",
    "Vmap",
    "batching_from_name",
    "block_lanes",
    "default_batching",
    "usable_cores",
)
