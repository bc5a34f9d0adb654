"""XLA compiler flags for processes that compile many small programs and run each
briefly: the ``heliojax`` command and the test suite set them for their own
process (an application's choice, before JAX starts its backend); the library
itself never changes a flag.

Since jaxlib 0.9.1 XLA's CPU backend generates code for fused operations with its
newer fusion emitters (openxla/xla issue 41173 traces a compile-time regression to
them). heliojax's programs compile 2-3x faster with the older emitters
(``--xla_cpu_use_fusion_emitters=false``; the change-point scan 4.7 -> 2.8 s, the
Levenberg-Marquardt fit of a new shape bucket 4.8 -> 2.5 s) and the fit of 1,000
heliostats x 100 records runs ~20 % slower (1.08 -> 1.32 s; both from
``benchmarks/calibration_speed.py``, one run each on 2 cores; on an idle machine on
2026-12-05, 5 repeats, 0.213 -> 0.225 s and the fit's compile 2.3 -> 1.45 s). GPUs
ignore the flag.

The library sets no flag. It compiles its own short-lived CPU programs (the
calibration fit, :class:`heliojax._programs.cached_jit`) with the same option given
to that compilation alone (:func:`cpu_compiler_options`); long-running programs (the
ray tracer, the neural correction's training) keep XLA's defaults.

Programs that a command runs once or a few times on small inputs (loading, evaluation,
the change-point scan: ``cached_jit(fn, quick=True)``) are compiled at XLA's backend
optimisation level 0 as well (:data:`QUICK_OPTION`): on the 8 x 192 records of the
embedded data the residual Jacobians compile in 0.29 s instead of 0.81 s and run in
13.9 instead of 6.5 ms, the change-point scan 0.28 s instead of 0.96 s and 3.7 instead
of 1.2 ms (one run each, 2-core CPU, 2026-12-06). Level 0 is worth it only while the
run is short: at 1,000 x 192 records the Jacobians' run grows from 0.77 s to 1.20 s, so
the choice is made per call by the size of the inputs
(:data:`heliojax._programs.QUICK_MAX_ELEMENTS`). The Levenberg-Marquardt fit, which runs
many steps, and discovery's lane programs, which run many times, keep the default level.
"""

from __future__ import annotations

import importlib.metadata
import os

from ._version import release_tuple

LEGACY_CPU_EMITTERS = "--xla_cpu_use_fusion_emitters=false"
"""The flag (see the module docstring)."""

FIRST_JAXLIB = (0, 9, 1)
"""The first jaxlib with the newer emitters; older ones do not need the flag."""


def _jaxlib_version() -> tuple[int, ...]:
    try:
        text = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return ()
    return release_tuple(text)[:3]


PROGRAM_OPTION = "xla_cpu_use_fusion_emitters"
"""The same XLA option, as a per-program compiler option (:func:`cpu_compiler_options`)."""


QUICK_OPTION = "xla_backend_optimization_level"
"""XLA's backend optimisation level, set to 0 for the quick programs (see the module
docstring)."""


def cpu_compiler_options(*, quick: bool = False) -> dict[str, bool | int]:
    """XLA options for heliojax's own CPU programs (the calibration fit and the
    programs of :class:`heliojax._programs.cached_jit`: many small programs, each run
    briefly), given to their compilation alone (``jax.jit``'s ``compiler_options``),
    so that no flag of the process changes: the older fusion emitters
    (``{"xla_cpu_use_fusion_emitters": False}``, see the module docstring), left out
    where ``XLA_FLAGS`` sets that option already (the user's choice, or the
    command's, wins) or the installed jaxlib predates the newer emitters. With
    ``quick`` (a program run once on small inputs) also optimisation level 0
    (``{"xla_backend_optimization_level": 0}``), unless ``XLA_FLAGS`` sets the level.
    Read from the environment when called."""
    flags = os.environ.get("XLA_FLAGS", "")
    options: dict[str, bool | int] = {}
    if PROGRAM_OPTION not in flags and _jaxlib_version() >= FIRST_JAXLIB:
        options[PROGRAM_OPTION] = False
    if quick and QUICK_OPTION not in flags:
        options[QUICK_OPTION] = 0
    return options


def with_fast_cpu_compilation(xla_flags: str) -> str:
    """``xla_flags`` (the ``XLA_FLAGS`` value) with :data:`LEGACY_CPU_EMITTERS`
    added, unless it already sets that option (the user's choice wins) or the
    installed jaxlib predates the newer emitters."""
    if "xla_cpu_use_fusion_emitters" in xla_flags or _jaxlib_version() < FIRST_JAXLIB:
        return xla_flags
    return f"{xla_flags} {LEGACY_CPU_EMITTERS}".strip()


__all__ = ["LEGACY_CPU_EMITTERS", "PROGRAM_OPTION", "QUICK_OPTION", "cpu_compiler_options", "with_fast_cpu_compilation"]
