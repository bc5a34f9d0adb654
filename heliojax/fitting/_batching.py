"""How the heliostat axis of a fit is batched: small frozen strategy objects.

Every strategy maps a per-heliostat function over the leading axis of its
arguments inside one compiled program:

* :class:`Vmap` - ``jax.vmap``: wide batches, for GPUs (a batched while loop runs
  every lane until the slowest converges).
* :class:`LaxMap` - ``jax.lax.map``: lanes one after another, best on CPU.
* :class:`Chunked` - ``lax.map`` over chunks of ``size`` lanes that are vmapped.
* :class:`Sharded` - the heliostat axis split over devices (see
  :mod:`heliojax.fitting._sharding`), each device batching its block by ``inner``.

:func:`default_batching` is the one place where a backend picks a strategy.
"""

from __future__ import annotations

import abc
import math
import typing
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

AXIS = "heliostats"
"""Name of the mesh axis the heliostats are sharded over."""


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
        if self.restart_after is not None and self.restart_after < 1:
            raise ValueError(f"Vmap: restart_after must be >= 1 or None, got {self.restart_after}")

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
        if self.size < 1:
            raise ValueError(f"Chunked: size must be >= 1, got {self.size}")

    def map(self, fn):
        return lambda *xs: jax.lax.map(lambda a: fn(*a), xs, batch_size=self.size)


RESTART_AFTER = 12
"""First-pass steps of the default :class:`Vmap`: about twice the median number of
steps (5) of simulated fleets; at 100,000 x 100 records the 99th percentile was 16
steps and the slowest lane 35, so 1-2 % of the lanes go on to the second pass."""


def default_batching(backend: str | None = None) -> AbstractBatching:
    """:class:`LaxMap` on CPU (sequential lanes beat vmap's lock-step while loop
    there), :class:`Vmap` on accelerators, restarting the lanes that have not
    converged after :data:`RESTART_AFTER` steps."""
    backend = backend or jax.default_backend()
    return LaxMap() if backend == "cpu" else Vmap(restart_after=RESTART_AFTER)


BATCHING_NAMES = ("auto", "vmap", "chunked", "map")


def batching_from_name(name: str, chunk_size: int = 64) -> AbstractBatching:
    """The strategy called ``name`` (``"auto" | "vmap" | "chunked" | "map"``), as the
    CLI and configs name them."""
    if name == "auto":
        return default_batching()
    if name == "vmap":
        return Vmap()
    if name == "map":
        return LaxMap()
    if name == "chunked":
        return Chunked(chunk_size)
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
    "Sharded",
    "Vmap",
    "batching_from_name",
    "default_batching",
)
