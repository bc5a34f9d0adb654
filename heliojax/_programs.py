"""Traced programs kept across processes (``jax.export``), beside JAX's persistent
compilation cache.

JAX's persistent cache skips *compiling* a program a second time, but a new
process still *traces* and lowers it: for the Levenberg-Marquardt fit of a fleet
that is ~2 s of the CLI's wall time. When a compilation cache directory is
configured (``jax.config.update("jax_compilation_cache_dir", DIR)``, as the CLI
does), :func:`compile_cached` also keeps the traced program, serialised with
:func:`jax.export.export`, in ``DIR/heliojax-programs/`` and loads it instead of
tracing again. The key is a SHA-256 of the function's name, everything static in
its arguments (pickled: solver settings, parameter views, model classes and
static fields), the shapes and dtypes of its array arguments, the versions of
heliojax, jax and jaxlib, a digest of heliojax's source files and the backend,
so a changed option, shape, version or source never reuses a program.
Arguments that cannot be pickled, and any failure to export or load, fall back
to tracing (the result is the same either way); a kept program records its key and
is used only under that key and for arguments of its input shapes and dtypes.

:func:`warm_up` runs work that compiles programs (e.g. a later stage of a workflow on
placeholder arrays of the right shapes) in a background thread, so that XLA compiles
them on another core while the caller goes on; a program being compiled there is
waited for, not compiled twice, when the caller needs it.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import hashlib
import logging
import pickle
import re
import threading
import typing
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
from jax.core import Tracer
from jaxlib import version as jaxlib_version

from ._io import atomic_write
from ._version import __version__

log = logging.getLogger(__name__)

PROGRAM_DIR = "heliojax-programs"
"""Subdirectory of the compilation cache directory holding the exported programs."""


@dataclasses.dataclass(frozen=True)
class _Leaf:
    """Placeholder for the ``index``-th array of a program's flattened output."""

    index: int


def _key(fn: typing.Any, stat: typing.Any, leaves: list) -> str | None:
    if "<" in fn.__qualname__:  # lambdas and local functions: the name does not identify them
        return None
    try:
        material = pickle.dumps(
            (
                fn.__module__,
                fn.__qualname__,
                stat,
                [(tuple(x.shape), str(x.dtype)) for x in leaves],
                __version__,
                source_digest(),
                jax.__version__,
                jaxlib_version.__version__,
                jax.default_backend(),
            ),
            protocol=5,
        )
    except Exception:  # noqa: BLE001 - unpicklable static parts (closures): no key, trace instead
        return None
    return hashlib.sha256(material).hexdigest()


@functools.cache
def source_digest() -> str:
    """SHA-256 of heliojax's own source files: an edited checkout (same version
    number, changed code) never loads a program traced from the old code."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def _program_dir() -> Path | None:
    directory = jax.config.jax_compilation_cache_dir  # pyright: ignore[reportAttributeAccessIssue]
    return None if not directory else Path(directory) / PROGRAM_DIR


def compile_cached(fn: Callable, *args: typing.Any) -> Callable[..., typing.Any]:
    """``fn`` (an :func:`equinox.filter_jit` function) compiled for ``args``,
    returned as a callable of the same arguments (of the same shapes and static
    parts). With a compilation cache directory configured, the traced program is
    loaded from / saved to it (see the module docstring); otherwise this is
    ``fn.lower(*args).compile()``. A program compiled once in this process (same
    key) is returned again without lowering or compiling (the CLI's calibration
    compiles one fit program and runs it for the fit, the drift's validation and
    the change-point refit)."""
    directory = _program_dir()
    dyn, stat = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree.flatten(dyn)
    key = _key(fn, stat, leaves)
    if key is None:
        return _compile(fn, args, stat, treedef, leaves, key, directory)
    mine: concurrent.futures.Future | None = None
    with _LOCK:
        program = _COMPILED.get(key)  # compiled in this process already
        pending = _PENDING.get(key) if program is None else None  # being compiled by another thread
        if program is None and pending is None:
            mine = _PENDING[key] = concurrent.futures.Future()
    if program is not None:
        return program
    if pending is not None:
        try:
            return pending.result()
        except Exception:  # noqa: BLE001 - that thread failed: compile here, raising what fails here
            return _compile(fn, args, stat, treedef, leaves, key, directory)
    assert mine is not None
    try:
        program = _compile(fn, args, stat, treedef, leaves, key, directory)
    except BaseException as e:
        with _LOCK:
            _PENDING.pop(key, None)
        mine.set_exception(e)
        raise
    with _LOCK:
        _COMPILED[key] = program
        _PENDING.pop(key, None)
    mine.set_result(program)
    return program


def _compile(
    fn: Callable, args: tuple, stat: typing.Any, treedef: typing.Any, leaves: list, key: str | None, directory
) -> Callable[..., typing.Any]:
    if directory is None or key is None:
        return fn.lower(*args).compile()  # pyright: ignore[reportAttributeAccessIssue]
    path = directory / f"{key}.bin"
    loaded = _load(path, leaves)
    if loaded is None:
        loaded = _export(fn, stat, treedef, leaves, path)
    if loaded is None:
        return fn.lower(*args).compile()  # pyright: ignore[reportAttributeAccessIssue]
    exported, skeleton = loaded
    try:
        program = jax.jit(exported.call).lower(*leaves).compile()
    except Exception as e:  # noqa: BLE001 - a program that does not take these arguments: trace instead
        log.debug("ignoring the cached program %s: %s", path, e)
        return fn.lower(*args).compile()  # pyright: ignore[reportAttributeAccessIssue]

    def run(*call_args: typing.Any) -> typing.Any:
        flat = jax.tree.leaves(eqx.filter(call_args, eqx.is_array))
        out = program(*flat)
        return jax.tree.map(lambda x: out[x.index] if isinstance(x, _Leaf) else x, skeleton)

    return run


def _export_allowing_version_bound_calls(flat: Callable, leaves: list) -> typing.Any:
    """Export ``flat``; custom calls without cross-version guarantees (LAPACK's QR on
    the CPU) are allowed, since the key pins the jax/jaxlib versions and backend."""
    specs = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
    allowed: set[str] = set()
    for _ in range(8):
        checks = [jax.export.DisabledSafetyCheck.custom_call(name) for name in sorted(allowed)]
        try:
            return jax.export.export(jax.jit(flat), disabled_checks=checks)(*specs)
        except ValueError as e:
            names = set(re.findall(r"custom_call @(\w+)", str(e))) - allowed
            if "compatibility guarantees" not in str(e) or not names:
                raise
            allowed |= names
    raise ValueError(f"too many custom calls without compatibility guarantees: {sorted(allowed)}")


@typing.final
class cached_jit(eqx.Module):
    """:func:`equinox.filter_jit` whose traced programs are kept across processes
    when a compilation cache directory is configured (see the module docstring);
    without one it is exactly ``eqx.filter_jit(fn)``. Use as a decorator."""

    fn: Callable = eqx.field(static=True)
    jitted: Callable = eqx.field(static=True)

    def __init__(self, fn: Callable):
        self.fn = fn
        self.jitted = eqx.filter_jit(fn)

    @property
    def __wrapped__(self) -> Callable:
        return self.fn

    def __call__(self, *args: typing.Any) -> typing.Any:
        if _program_dir() is None:
            return self.jitted(*args)
        dyn, stat = eqx.partition(args, eqx.is_array)
        leaves = jax.tree.leaves(dyn)
        if any(isinstance(x, Tracer) for x in leaves):  # inside another trace: a nested jit
            return self.jitted(*args)
        key = _key(self.fn, stat, leaves)
        if key is None:
            return self.jitted(*args)
        program = _COMPILED.get(key)
        if program is None:
            program = compile_cached(self.jitted, *args)
        return program(*args)


_COMPILED: dict[str, Callable] = {}
"""Programs compiled in this process by :class:`cached_jit`, by key (like jit's own cache)."""
_PENDING: dict[str, concurrent.futures.Future] = {}
"""Programs being compiled by a thread now, by key: another thread waits for them."""
_LOCK = threading.Lock()
_BACKGROUND: list[concurrent.futures.ThreadPoolExecutor] = []
_WARM_UP_THREAD = "heliojax-warm-up"


def warm_up(work: Callable[[], typing.Any]) -> concurrent.futures.Future:
    """Run ``work()`` (e.g. a later stage of a workflow on placeholder arrays of the
    shapes it will get) in a background thread, for the programs it compiles: a later
    call that needs one of them waits for it instead of compiling it again, and XLA
    compiles on another core meanwhile. Its result and failures are discarded (a
    failure is logged at debug level; the caller then compiles as usual). The thread
    sees the caller's ``jax_enable_x64``. Returns the future of ``work()``; wait on it
    before returning to the caller's own caller, so that no work outlives the call."""
    x64 = bool(jax.config.jax_enable_x64)  # pyright: ignore[reportAttributeAccessIssue]

    def run() -> None:
        try:
            with jax.enable_x64(x64):
                work()
        except Exception as e:  # noqa: BLE001 - only a head start: the caller compiles what failed here
            log.debug("warm-up of %s failed: %s", work, e)

    if threading.current_thread().name.startswith(_WARM_UP_THREAD):  # from a warm-up: no thread waits for itself
        done: concurrent.futures.Future = concurrent.futures.Future()
        run()
        done.set_result(None)
        return done
    with _LOCK:
        if not _BACKGROUND:
            _BACKGROUND.append(concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=_WARM_UP_THREAD))
    return _BACKGROUND[0].submit(run)


def _load(path: Path, leaves: list) -> tuple[typing.Any, typing.Any] | None:
    """The exported program and output skeleton kept in ``path``, or None when there
    is none, it is damaged, it was written under another key (a file renamed or
    copied over another), or its inputs are not the shapes and dtypes of ``leaves``."""
    try:
        blob = path.read_bytes()
    except OSError:
        return None
    try:
        key, skeleton_bytes, program_bytes = pickle.loads(blob)
        if key != path.stem:
            raise ValueError(f"written for the key {key!r}")
        exported = jax.export.deserialize(program_bytes)
        wanted = [(tuple(x.shape), str(x.dtype)) for x in leaves]
        if [(tuple(a.shape), str(a.dtype)) for a in exported.in_avals] != wanted:
            raise ValueError("its inputs are not these arguments' shapes and dtypes")
        return exported, pickle.loads(skeleton_bytes)
    except Exception as e:  # noqa: BLE001 - a stale or damaged entry: trace again and overwrite it
        log.debug("ignoring the cached program %s: %s", path, e)
        return None


def _export(fn: Callable, stat: typing.Any, treedef: typing.Any, leaves: list, path: Path):
    skeleton: list = []

    def flat(*flat_leaves):
        out = fn(*eqx.combine(jax.tree.unflatten(treedef, flat_leaves), stat))
        out_leaves, out_tree = jax.tree.flatten(out, is_leaf=lambda x: x is None)
        arrays = [x for x in out_leaves if eqx.is_array(x)]
        marks, n = [], 0
        for x in out_leaves:
            if eqx.is_array(x):
                marks.append(_Leaf(n))
                n += 1
            else:
                marks.append(x)
        skeleton.append(jax.tree.unflatten(out_tree, marks))
        return arrays

    try:
        exported = _export_allowing_version_bound_calls(flat, leaves)
        blob = pickle.dumps((path.stem, pickle.dumps(skeleton[0], protocol=5), exported.serialize()), protocol=5)
    except Exception as e:  # noqa: BLE001 - not exportable (e.g. an unsupported custom call): trace as usual
        log.debug("not keeping the traced program of %s: %s", fn, e)
        return None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path, "wb") as f:
            f.write(blob)
    except OSError as e:
        log.debug("cannot write %s: %s", path, e)
    return exported, skeleton[0]


__all__ = ["PROGRAM_DIR", "cached_jit", "compile_cached", "warm_up"]
