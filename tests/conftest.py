"""Test configuration: float64 on (calibration and geodesy need it), strict rank and
dtype promotion, shared-data paths (warnings are errors: ``filterwarnings`` in
pyproject.toml), XLA's costly optimisations off.

The suite is bound by XLA compilation: hundreds of distinct small programs, each run
a few times. ``JAX_DISABLE_MOST_OPTIMIZATIONS=1`` (backend optimisation level 0, no
expensive LLVM passes) compiles them ~1.6x faster; it is set in the environment, so
the CLI subprocesses and notebook kernels that tests start inherit it. The programs
compute the same values to rounding (no fast-math either way; the fit benchmark's
held-out RMS agreed to 1e-11 mrad). XLA's older CPU fusion emitters, as the
``heliojax`` command uses them (``heliojax._xla_flags``; ``XLA_FLAGS``, inherited
the same way), compile 2-3x faster again. Tests marked ``optimised`` do much
work per program (ray tracing, reconstruction) and run with the optimisations on.
(Discovery's tests were marked until 2026-11-29; its programs have since become
cheaper to run than to optimise: tests/test_discovery.py and
tests/test_discovery_paint.py took 92 s optimised and 81 s without, in one
process.) A run with everything optimised, as users get it, is
``JAX_DISABLE_MOST_OPTIMIZATIONS=0 python -m pytest -n 2 -q``.
"""

from __future__ import annotations

import gc
import logging
import os
import time
from pathlib import Path

os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")


from heliojax._xla_flags import with_fast_cpu_compilation  # noqa: E402  (imports no JAX)

os.environ["XLA_FLAGS"] = with_fast_cpu_compilation(os.environ.get("XLA_FLAGS", ""))


def _import_dependencies_first() -> None:
    """Import the libraries heliojax's modules import at their top level (and
    beartype's checker) before those modules run (``heliojax`` itself and
    ``heliojax._xla_flags``, above, import none of them; ``XLA_FLAGS`` is set before
    anything could start JAX's backend).

    jaxtyping's import hook (``--jaxtyping-packages``) runs each heliojax module with
    its own name for compiled bytecode (``*.opt-jaxtyping*.pyc``) for everything
    imported meanwhile; where bytecode is not written (``PYTHONDONTWRITEBYTECODE``),
    jax, scipy, beartype and the rest (~1,800 modules) were compiled from source in
    every worker, ~4-5 s each."""
    import ast
    import importlib

    names = {"beartype.door"}
    for path in (Path(__file__).resolve().parents[1] / "heliojax").rglob("*.py"):
        for node in ast.parse(path.read_bytes()).body:
            if isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module)
    for name in sorted(names):
        if name.partition(".")[0] not in ("heliojax", "__future__"):
            importlib.import_module(name)


_import_dependencies_first()


import jax  # noqa: E402  (reads JAX_* variables at import)
import jaxtyping  # noqa: E402
import pytest  # noqa: E402

import heliojax as hj  # noqa: E402

jax.config.update("jax_enable_x64", True)
# Catch silent broadcasting and mixed-dtype arithmetic in heliojax and in the tests.
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

SHARED_PAINT = Path(__file__).resolve().parents[2] / "shared" / "data" / "paint"


_CACHE_OPTIONS = (
    "jax_compilation_cache_dir",
    "jax_persistent_cache_min_compile_time_secs",
    "jax_persistent_cache_min_entry_size_bytes",
)


@pytest.fixture(autouse=True)
def _restore_cli_process_settings():
    """The CLI configures JAX's persistent cache (and with it heliojax's kept
    programs) and logging for its process; in the test process, undo both after
    each test."""
    before = {k: getattr(jax.config, k) for k in _CACHE_OPTIONS}
    yield
    for k, v in before.items():
        if getattr(jax.config, k) != v:
            jax.config.update(k, v)
    logger = logging.getLogger("heliojax")  # and the CLI's stderr handler
    for handler in list(logger.handlers):
        logger.removeHandler(handler)
    logger.propagate = True
    logger.setLevel(logging.NOTSET)


@pytest.fixture(scope="session", autouse=True)
def _compilation_cache_of_the_session(tmp_path_factory):
    """The CLI run in the test process, in subprocesses and in notebook kernels keeps
    its compiled programs in a folder of this test session (``$HELIOJAX_CACHE_DIR``,
    one per xdist worker), not in the user's ``~/.cache/heliojax``: the tests leave
    nothing in the home folder, and a run starts as cold as on a fresh machine (CI)."""
    with pytest.MonkeyPatch.context() as session:
        session.setenv("HELIOJAX_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "heliojax-cache"))
        yield


_optimised_now = [False]  # this process's last setting; programs compiled before a switch are reused


@pytest.fixture(autouse=True)
def _optimised_when_marked(request, monkeypatch):
    """XLA's optimisations back on (in this process and its children) for tests
    marked ``optimised``. On the switch to optimised, JAX's in-memory caches are
    cleared (its jit cache does not key on the setting, so unoptimised programs of
    earlier tests would be reused); consecutive marked tests share their programs. A
    test marked ``optimised(kernel_only=True)`` compiles nothing in this process (a
    notebook runs in its own kernel, which reads the environment): this process keeps
    its setting and its programs."""
    marker = request.node.get_closest_marker("optimised")
    marked = marker is not None
    default = os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] != "0"
    if marked:
        monkeypatch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "0")
    if marked and marker.kwargs.get("kernel_only", False):  # only a notebook kernel compiles
        yield
        return
    if marked and default and not _optimised_now[0]:
        jax.clear_caches()
    jax.config.update("jax_disable_most_optimizations", default and not marked)
    _optimised_now[0] = marked or not default
    yield


MAP_HEADROOM = 0.6
"""Share of Linux's per-process limit on memory mappings (``vm.max_map_count``) at
which a worker drops its compiled programs (see :func:`_programs_dropped_before_the_limit`).
The rest (26,000 of 65,530) must hold what one test adds: a whole ``discover`` of the
real records in a fresh process ended at 14,909 mappings."""


@pytest.fixture(autouse=True)
def _programs_dropped_before_the_limit():
    """After a test, if this process's memory mappings pass :data:`MAP_HEADROOM` of the
    limit, drop the compiled programs it keeps (:func:`heliojax.clear_caches`).

    Each compiled XLA:CPU program holds ~3-6 mappings while it is cached; a worker of
    ``-n 2`` reached the limit (65,530) at ~85 % of the suite (~12,000 programs), and
    XLA's compiler then died of a segmentation fault (the "intermittent" crash of
    earlier sessions, in whichever test compiled next), after which pytest-xdist
    (``--dist loadfile``) waits for ever. Dropping the programs costs their
    recompilation in later tests that would have reused them."""
    yield
    now = time.monotonic()
    if now - _last_map_check[0] < MAP_CHECK_INTERVAL_S:
        return
    _last_map_check[0] = now
    count = hj.memory_map_count()
    if count is not None and count[0] > MAP_HEADROOM * count[1]:
        hj.clear_caches()
        gc.collect()


MAP_CHECK_INTERVAL_S = 10.0
"""Least wall time between two counts of the mappings: a count reads ``/proc/self/maps``
(~20 ms at 20,000 mappings, ~40 ms at 40,000; after each of a worker's ~630 tests that
was ~15-25 s per worker). A worker adds at most a few hundred mappings a second (~170 on
average over its busiest two minutes), so 10 s and the longest test (~30 s) stay far
within the headroom."""
_last_map_check = [0.0]


@pytest.fixture
def unchecked():
    """Run-time type checks off, for tests that hand heliojax ill-typed values on
    purpose to see its own validation errors (what a user without checks gets)."""
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", False)


@pytest.fixture(scope="session")
def fitted_h5(tmp_path_factory) -> Path:
    """A results.h5 of the embedded data (a quick stone8 fit: 3 steps), read-only."""
    from heliojax.cli._main import main

    results = tmp_path_factory.mktemp("fitted") / "results.h5"
    argv = ["calibrate", "--model", "stone8", "--max-steps", "3", "--out", str(results), "--cache-dir", "none"]
    assert main([*argv, "--quiet"]) == 0
    return results


@pytest.fixture(scope="session")
def shared_paint() -> Path:
    """The real PAINT records beside the checkout (../shared/data/paint)."""
    if not (SHARED_PAINT / "WRI1030197-tower-measurements.json").exists():
        pytest.skip(f"shared PAINT data not found at {SHARED_PAINT}")
    return SHARED_PAINT


def pytest_collection_modifyitems(config, items):
    """Start each xdist worker's share with half of the notebook runs (the longest
    tests, ~20-60 s each, no shared fixtures): work stealing then evens out the
    short tests at the end instead of one worker finishing a notebook alone.

    The tests marked ``optimised`` come next, together, in the first share (each share's
    notebooks end with an optimised one): a switch to the optimised setting clears
    JAX's caches in the process, so optimised files between unoptimised ones dropped
    the programs compiled so far (test_discovery_paint, then marked, had recompiled the
    discovery programs test_discovery had compiled, optimised, before test_discovery_lanes)."""
    if not config.pluginmanager.hasplugin("xdist") or not getattr(config.option, "numprocesses", None):
        return
    heavy = [it for it in items if it.nodeid.startswith("tests/test_notebook_")]
    rest = [it for it in items if not it.nodeid.startswith("tests/test_notebook_")]
    optimised = [it.get_closest_marker("optimised") is not None for it in rest]
    rest = [it for it, o in zip(rest, optimised) if o] + [it for it, o in zip(rest, optimised) if not o]
    split = len(items) // 2 - len(heavy[::2])
    items[:] = heavy[::2] + rest[:split] + heavy[1::2] + rest[split:]


@pytest.fixture(autouse=True)
def _figures_are_readable(monkeypatch):
    """Every figure a test saves is checked first (labels, colour bars, nothing cut
    off; see tests/_figure_check.py)."""
    from _figure_check import checked_savefig
    from matplotlib.figure import Figure

    monkeypatch.setattr(Figure, "savefig", checked_savefig)
