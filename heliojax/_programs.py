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

Loading an exported program still lowers it again and looks it up in JAX's cache
(~0.05-0.1 s per program). So the compiled executable is kept as well
(:mod:`jax.experimental.serialize_executable`, ``DIR/heliojax-programs/*.exe``),
keyed by the program's key and everything else the compiler's output depends on
(XLA's flags, JAX's optimisation settings, the device, the host processor), with a
digest of its bytes checked before XLA reads them; only executables compiled in
this process are kept (see :func:`_compile_noting_cache_hits`). A command lists the
executables it ran (:func:`remember`); its next run loads them in a background
thread while it imports and reads its data (:func:`preload`). The warm
``heliojax calibrate`` on the embedded data: 2.2-2.7 s before, 1.9-2.3 s with
both (interleaved runs, 2-core CPU).

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
import io
import logging
import os
import pickle
import platform
import re
import threading
import typing
from collections.abc import Callable, Iterable
from pathlib import Path

import equinox as eqx
import jax
from jax._src import core as jax_core
from jax.core import Tracer
from jax.experimental import serialize_executable
from jaxlib import version as jaxlib_version

from ._io import atomic_write
from ._version import __version__
from ._xla_flags import cpu_compiler_options

log = logging.getLogger(__name__)

PROGRAM_DIR = "heliojax-programs"
"""Subdirectory of the compilation cache directory holding the exported programs."""

EXECUTABLE_SUFFIX = ".exe"
"""File name ending of a kept compiled executable (beside the exported ``.bin``)."""

EXECUTABLE_BACKENDS = ("cpu",)
"""Backends whose compiled executables are kept: the CPU's, where the command line's
wait is (and where loading them was tested: on XLA:CPU an executable needs its LAPACK
kernels bound, the device it was compiled for, and must not come from JAX's cache).
Elsewhere the kept traced programs are compiled (or found in JAX's cache) as before."""


@dataclasses.dataclass(frozen=True)
class _Leaf:
    """Placeholder for the ``index``-th array of a program's flattened output."""

    index: int


def _signature(arrays: Iterable[typing.Any]) -> list[tuple[tuple[int, ...], str]]:
    """The shapes and dtypes of ``arrays`` (arrays or abstract values): what a kept
    program's inputs must match."""
    return [(tuple(x.shape), str(x.dtype)) for x in arrays]


def _key(fn: typing.Any, stat: typing.Any, leaves: list) -> str | None:
    if "<" in fn.__qualname__:  # lambdas and local functions: the name does not identify them
        return None
    material = io.BytesIO()
    pickler = pickle.Pickler(material, protocol=5)
    # no memo: equal static parts give equal bytes whether or not they share objects (a
    # program's outputs share the static parts of its inputs when traced here, not when
    # loaded, which gave a second run of the CLI other keys than the first)
    pickler.fast = True
    try:
        pickler.dump(
            (
                fn.__module__,
                fn.__qualname__,
                stat,
                _signature(leaves),
                __version__,
                source_digest(),
                jax.__version__,
                jaxlib_version.__version__,
                jax.default_backend(),
            )
        )
    except Exception:  # noqa: BLE001 - unpicklable static parts (closures), a cycle: no key, trace instead
        return None
    return hashlib.sha256(material.getvalue()).hexdigest()


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
    options = fn.compiler_options(leaves) if isinstance(fn, program_jit) else _compiler_options()
    executable_path = None
    if jax.default_backend() in EXECUTABLE_BACKENDS:
        executable_path = directory / f"{_executable_key(key, leaves, options)}{EXECUTABLE_SUFFIX}"
    kept = None if executable_path is None else _load_executable(executable_path, leaves)
    if kept is not None and executable_path is not None:
        program, skeleton = kept
        _note_used(executable_path)
    else:
        path = directory / f"{key}.bin"
        loaded = _load(path, leaves)
        if loaded is None:
            loaded = _export(fn, stat, treedef, leaves, path)
        if loaded is None:
            return fn.lower(*args).compile()  # pyright: ignore[reportAttributeAccessIssue]
        exported, skeleton = loaded
        try:
            # a program JAX's cache already holds (compiled under another key) is not kept:
            # compiling it afresh to keep it cost a cold discovery on the shared records
            # ~27 s and saved its warm run nothing
            call = jax.jit(exported.call, compiler_options=options)
            program, fresh = _compile_noting_cache_hits(call.lower(*leaves))
        except Exception as e:  # noqa: BLE001 - a program that does not take these arguments: trace instead
            log.debug("ignoring the cached program %s: %s", path, e)
            return fn.lower(*args).compile()  # pyright: ignore[reportAttributeAccessIssue]
        if fresh and executable_path is not None and _keep_executable(executable_path, program, skeleton):
            _note_used(executable_path)

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


QUICK_MAX_ELEMENTS = 2**18
"""A quick program (``cached_jit(fn, quick=True)``) is compiled at XLA's optimisation
level 0 when its array arguments hold at most this many elements together: there its
run takes at most a few tens of milliseconds more (the residual Jacobians of 8 x 192
records 6.5 -> 13.9 ms, of 1,000 x 192 records 0.77 -> 1.20 s, i.e. ~0.4 s more per
3 million elements; 2-core CPU), while its compile takes 0.2-0.7 s less
(:mod:`heliojax._xla_flags`)."""


def _inside_a_trace(args: typing.Any) -> bool:
    """Whether a call with ``args`` is being traced into another program (a caller's
    ``jax.jit``, ``vmap`` or ``grad``, a ``lax.scan`` body, an export): an argument is a
    tracer, or JAX is tracing now, as inside a caller's ``jax.jit`` whose arrays reach
    the call as constants (closed over, or ``static_argnums``), not as arguments."""
    if any(isinstance(x, Tracer) for x in jax.tree.leaves(args)):
        return True
    context = getattr(jax_core, "trace_ctx", None)  # jax >= 0.4.36
    if context is not None:
        return not context.is_top_level()
    return not jax_core.trace_state_clean()  # pyright: ignore[reportAttributeAccessIssue]


def _array_elements(args: typing.Any) -> int:
    return sum(int(x.size) for x in jax.tree.leaves(args) if eqx.is_array(x))


@typing.final
class program_jit:
    """:func:`equinox.filter_jit` of ``fn`` whose compilation for the CPU gets the
    XLA options of :func:`heliojax._xla_flags.cpu_compiler_options` (XLA's older
    fusion emitters: the fit compiles in ~1.45 s instead of ~2.3 s, and runs ~5 %
    slower), given to this program's compilation alone: no flag of the process
    changes, and other backends compile it with XLA's defaults. With ``quick`` (a
    program run once or a few times per command, not an inner loop), a call whose
    array arguments hold at most :data:`QUICK_MAX_ELEMENTS` elements is compiled at
    XLA's optimisation level 0 too. Use as a decorator; called, or lowered
    (``.lower(*args)``), like the jitted function."""

    def __init__(self, fn: Callable, *, quick: bool = False):
        functools.update_wrapper(self, fn)
        self._fn = fn
        self.quick = quick
        self._default = eqx.filter_jit(fn)
        self._cpu: dict[bool, Callable] = {}
        self._lock = threading.Lock()

    def _is_quick(self, args: typing.Any) -> bool:
        return self.quick and _array_elements(args) <= QUICK_MAX_ELEMENTS

    def compiler_options(self, args: typing.Any) -> dict[str, bool | int] | None:
        """The XLA options this program is compiled with for ``args`` (None: XLA's defaults)."""
        return _compiler_options(quick=self._is_quick(args))

    def _jitted(self, quick: bool = False) -> typing.Any:
        jitted = self._cpu.get(quick)
        if jitted is None:
            with self._lock:
                jitted = self._cpu.get(quick)
                if jitted is None:
                    options = _compiler_options(quick=quick)  # the rule shared with the kept programs
                    jit_options: dict[str, typing.Any] = {"compiler_options": options}  # to jax.jit
                    jitted = self._cpu[quick] = eqx.filter_jit(self._fn, **jit_options) if options else self._default
        return jitted

    def __call__(self, *args: typing.Any) -> typing.Any:
        leaves = jax.tree.leaves(args)  # flattened once for both checks
        if _inside_a_trace(leaves):
            # inside another trace (a caller's jit, or an export): JAX takes compiler
            # options at the top level only, where the caller's program gets its own
            return self._default(*args)
        return self._jitted(self._is_quick(leaves))(*args)

    def lower(self, *args: typing.Any) -> typing.Any:
        return self._jitted(self._is_quick(args)).lower(*args)


@typing.final
class cached_jit(eqx.Module):
    """:class:`program_jit` whose traced programs are kept across processes when a
    compilation cache directory is configured (see the module docstring); without
    one it is exactly ``program_jit(fn, quick=quick)``. Use as a decorator
    (``@functools.partial(cached_jit, quick=True)`` for a program run once or a few
    times per command, see :class:`program_jit`)."""

    fn: Callable = eqx.field(static=True)
    jitted: Callable = eqx.field(static=True)

    def __init__(self, fn: Callable, *, quick: bool = False):
        self.fn = fn
        self.jitted = program_jit(fn, quick=quick)

    @property
    def __wrapped__(self) -> Callable:
        return self.fn

    def __call__(self, *args: typing.Any) -> typing.Any:
        if _program_dir() is None:
            return self.jitted(*args)
        dyn, stat = eqx.partition(args, eqx.is_array)
        leaves = jax.tree.leaves(dyn)
        if _inside_a_trace(leaves):  # a nested jit: part of the caller's program, not kept apart
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


def clear_caches() -> None:
    """Drop every compiled program this process keeps: heliojax's (:class:`cached_jit`'s
    programs of this process) and JAX's (:func:`jax.clear_caches`); later calls compile
    (or load from a configured persistent cache) again. Programs being compiled by a
    warm-up thread now are kept.

    For a long-running process that compiles many distinct programs (a notebook, a
    service, a test suite): XLA:CPU maps each compiled program's code and data into
    memory as separate memory mappings (~5-20 per program as measured), kept while the
    program is cached, and Linux limits a process to ``vm.max_map_count`` mappings
    (65,530 by default). XLA's compiler dies of a segmentation fault, with no Python
    error, when a new program finds that limit reached: a test suite's worker did after
    ~13,000 programs (:func:`memory_map_count` says how near a process is)."""
    with _LOCK:
        _COMPILED.clear()
    jax.clear_caches()


def memory_map_count() -> tuple[int, int] | None:
    """``(mappings in use, the limit)``: this process's memory mappings
    (``/proc/self/maps``) and Linux's ``vm.max_map_count``; None where either cannot
    be read (not Linux). See :func:`clear_caches`."""
    try:
        with open("/proc/self/maps", "rb") as f:
            used = sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b""))
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None
    return used, limit


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
        if _signature(exported.in_avals) != _signature(leaves):
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


@functools.cache
def _host_processor() -> str:
    """The host CPU's model and instruction-set extensions (Linux: ``/proc/cpuinfo``;
    elsewhere what :mod:`platform` knows): XLA compiles CPU programs for the features
    of the processor it runs on, so a cache folder shared between machines (a network
    home folder) must not hand one machine's executables to another."""
    try:
        lines = Path("/proc/cpuinfo").read_text(errors="replace").splitlines()
    except OSError:
        lines = []
    wanted = ("model name", "flags", "Features", "CPU implementer", "CPU part")
    found = {}
    for line in lines:
        name, _, value = line.partition(":")
        if name.strip() in wanted:
            found.setdefault(name.strip(), value.strip())
    return repr((platform.machine(), platform.processor(), sorted(found.items())))


_COMPILE_SETTINGS = (
    "jax_enable_x64",
    "jax_default_matmul_precision",
    "jax_disable_most_optimizations",
    "jax_optimization_level",
    "jax_exec_time_optimization_effort",
    "jax_memory_fitting_level",
    "jax_memory_fitting_effort",
)
"""JAX settings that change what XLA compiles from a given program."""


def _executable_key(key: str, leaves: list, options: dict[str, bool | int] | None) -> str:
    """The key of the compiled executable of the program kept under ``key`` for the
    arrays ``leaves``: that key and everything the compiler's output depends on
    besides the program (XLA's flags and the program's ``options``, JAX's optimisation setting, the devices the
    arrays are on, the default device, the platform's version and the host
    processor)."""
    device = jax.devices()[0]  # the backend compiling this program has started already
    placed = sorted({d.id for x in leaves if isinstance(x, jax.Array) for d in x.devices()})
    material = (
        key,
        placed,
        str(jax.config.values.get("jax_default_device")),
        os.environ.get("XLA_FLAGS", ""),
        options,
        [(name, jax.config.values.get(name)) for name in _COMPILE_SETTINGS],
        device.platform,
        device.device_kind,
        device.client.platform_version,
        jax.device_count(),
        _host_processor(),
    )
    return hashlib.sha256(repr(material).encode()).hexdigest()


def _compiler_options(*, quick: bool = False) -> dict[str, bool | int] | None:
    """The XLA options :class:`program_jit` gives a program compiled now (None: XLA's
    defaults); ``quick``: a quick program's call on small inputs."""
    return (cpu_compiler_options(quick=quick) or None) if jax.default_backend() == "cpu" else None


_CACHE_HIT = "/jax/compilation_cache/cache_hits"
"""The :mod:`jax.monitoring` event of a program loaded from JAX's persistent cache."""


def _compile_noting_cache_hits(lowered: typing.Any) -> tuple[typing.Any, bool]:
    """``lowered.compile()`` and whether XLA compiled it here, not loaded from JAX's
    persistent cache. On XLA:CPU an executable that JAX loaded from its cache
    serialises without its kernels (run in another process: "Function ... not
    found"), so only freshly compiled ones are kept."""
    me = threading.get_ident()
    hits: list[str] = []

    def listen(event: str, **_: typing.Any) -> None:
        if event == _CACHE_HIT and threading.get_ident() == me:  # not another thread's compile
            hits.append(event)

    jax.monitoring.register_event_listener(listen)
    try:
        return lowered.compile(), not hits
    finally:
        jax.monitoring.unregister_event_listener(listen)


def _keep_executable(path: Path, program: typing.Any, skeleton: typing.Any) -> bool:
    """Write ``program`` (a :class:`jax.stages.Compiled` of a flat list of arrays)
    to ``path``, with its output skeleton, the device it runs on and a digest of the
    executable's bytes; whether it was written (a program over several devices and
    an executable that cannot be serialised, e.g. on a backend without support, are
    not kept)."""
    try:
        shardings = jax.tree.leaves((program.input_shardings, program.output_shardings))
        devices = {d.id for sharding in shardings for d in sharding.device_set}
        if len(devices) != 1:  # loading needs the devices it runs on, in order: only one is unambiguous
            raise ValueError(f"it runs on {len(devices)} devices")
        executable, in_tree, out_tree = serialize_executable.serialize(program)
        digest = hashlib.sha256(executable).hexdigest()
        blob = pickle.dumps((path.stem, digest, executable, in_tree, out_tree, skeleton, devices.pop()), protocol=5)
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path, "wb") as f:
            f.write(blob)
    except Exception as e:  # noqa: BLE001 - only a cost: the next process lowers and compiles again
        log.debug("not keeping the executable %s: %s", path, e)
        return False
    return True


@functools.cache
def _native_kernels_bound() -> bool:
    """Whether jaxlib's LAPACK kernels are bound. JAX binds them lazily, when a program
    that calls them is lowered (or an exported one is called): an executable loaded
    without either would call unbound kernels and crash the process. This binds them
    as :mod:`jax.export` does before a call (a JAX-internal function; where it is
    missing, no executable is loaded)."""
    try:
        from jax._src.lax import linalg

        linalg.initialize_lapack()
    except Exception as e:  # noqa: BLE001 - another JAX: lower and compile instead
        log.debug("not loading kept executables: %s", e)
        return False
    return True


def _load_executable(path: Path, leaves: list) -> tuple[typing.Any, typing.Any] | None:
    """The compiled program and output skeleton kept in ``path`` (loaded by
    :func:`preload` or read now), or None when there is none, it is damaged, or it
    takes other shapes or dtypes than ``leaves``."""
    with _LOCK:
        preloaded = _PRELOADED.pop(path, None)
    kept = preloaded.result() if preloaded is not None else _read_executable(path)
    if kept is None:
        return None
    if _signature(jax.tree.leaves(kept[0].in_avals)) != _signature(leaves):
        log.debug("ignoring the kept executable %s: its inputs are not these arguments' shapes and dtypes", path)
        return None
    return kept


def _read_executable(path: Path) -> tuple[typing.Any, typing.Any] | None:
    """The compiled program and output skeleton kept in ``path``, or None when there is
    none, its bytes are not the ones written (the digest is checked before XLA reads
    them) or it was written under another key."""
    try:
        blob = path.read_bytes()
    except OSError:
        return None
    if not _native_kernels_bound():
        return None
    try:
        key, digest, executable, in_tree, out_tree, skeleton, device_id = pickle.loads(blob)
        if key != path.stem:
            raise ValueError(f"written for the key {key!r}")
        if hashlib.sha256(executable).hexdigest() != digest:
            raise ValueError("its bytes are not the ones written")
        (device,) = [d for d in jax.devices() if d.id == device_id]  # the device it was compiled for
        program = serialize_executable.deserialize_and_load(executable, in_tree, out_tree, execution_devices=[device])
        return program, skeleton
    except Exception as e:  # noqa: BLE001 - stale or damaged: lower and compile again, and overwrite it
        log.debug("ignoring the kept executable %s: %s", path, e)
        return None


RECENT_SUFFIX = ".recent"
"""File name ending of the list of executables a command ran (see :func:`preload`)."""

_PRELOADED: dict[Path, concurrent.futures.Future] = {}
"""Kept executables loaded (or being loaded) by :func:`preload`, not yet asked for."""
_USED: dict[Path, None] = {}
"""The kept executables this process ran since the last :func:`preload`, in order."""


def _note_used(path: Path) -> None:
    with _LOCK:
        _USED[path] = None


def preload(name: str) -> None:
    """A command named ``name`` starts: load the kept executables that its last run
    ran (as :func:`remember` listed them in ``name.recent`` of the program directory)
    in a background thread, while the command imports, reads its data and prepares
    its arrays, so that its calls find them loaded (~0.3 s of the warm
    ``heliojax calibrate``). An executable listed but not asked for costs only the
    background thread's time; one asked for before it is loaded is waited for. Does
    nothing without a compilation cache directory. What an earlier command's
    :func:`preload` loaded and it never asked for is let go."""
    directory = _program_dir()
    with _LOCK:
        _USED.clear()
        _PRELOADED.clear()  # an earlier command's executables that it never asked for
    if directory is None:
        return
    try:
        names = (directory / f"{name}{RECENT_SUFFIX}").read_text().split()
    except (OSError, UnicodeDecodeError):
        return
    pending = []
    with _LOCK:
        for entry in names:
            path = directory / entry
            if re.fullmatch(r"[0-9a-f]{64}" + re.escape(EXECUTABLE_SUFFIX), entry) and path not in _PRELOADED:
                _PRELOADED[path] = future = concurrent.futures.Future()
                pending.append((path, future))

    def load() -> None:
        for path, future in pending:
            if not threading.main_thread().is_alive():  # the interpreter is exiting: load nothing more
                future.set_result(None)
                continue
            try:
                future.set_result(_read_executable(path))
            except BaseException as e:  # noqa: BLE001 - _read_executable returns None on failure; just in case
                future.set_result(None)
                log.debug("preloading %s failed: %s", path, e)

    if pending:
        # Not a daemon: the interpreter's exit waits for the executable being read, and
        # the thread then stops. A daemon thread inside XLA's deserializer when a Python
        # caller's interpreter exited (two commands through heliojax.cli._main.main in one
        # process) was ended inside C++ code: "terminate called ... FATAL: exception not
        # rethrown", exit status 134 (hostile-input round 11). The heliojax program itself
        # ends with os._exit and waits for nothing.
        threading.Thread(target=load, name=_PRELOAD_THREAD, daemon=False).start()


_PRELOAD_THREAD = "heliojax-preload"


def remember(name: str) -> None:
    """List the kept executables this process ran since :func:`preload` (in order) in
    ``name.recent`` of the program directory, for the next run's :func:`preload`."""
    directory = _program_dir()
    with _LOCK:
        used = [p.name for p in _USED if p.parent == directory]
    if directory is None or not used:
        return
    try:
        with atomic_write(directory / f"{name}{RECENT_SUFFIX}", "w") as f:
            f.write("\n".join(used) + "\n")
    except OSError as e:
        log.debug("cannot write the list of programs %s: %s", name, e)


__all__ = [
    "EXECUTABLE_SUFFIX",
    "PROGRAM_DIR",
    "RECENT_SUFFIX",
    "cached_jit",
    "clear_caches",
    "compile_cached",
    "memory_map_count",
    "preload",
    "remember",
    "warm_up",
]
