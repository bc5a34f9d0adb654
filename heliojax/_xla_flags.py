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
"""

from __future__ import annotations

import importlib.metadata
import os
import re

LEGACY_CPU_EMITTERS = "--xla_cpu_use_fusion_emitters=false"
"""The flag (see the module docstring)."""

FIRST_JAXLIB = (0, 9, 1)
"""The first jaxlib with the newer emitters; older ones do not need the flag."""


def _jaxlib_version() -> tuple[int, ...]:
    try:
        text = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return ()
    return tuple(int(x) for x in re.findall(r"\d+", text)[:3])


PROGRAM_OPTION = "xla_cpu_use_fusion_emitters"
"""The same XLA option, as a per-program compiler option (:func:`cpu_compiler_options`)."""


def cpu_compiler_options() -> dict[str, bool]:
    """XLA options for heliojax's own CPU programs (the calibration fit and the
    programs of :class:`heliojax._programs.cached_jit`: many small programs, each run
    briefly), given to their compilation alone (``jax.jit``'s ``compiler_options``),
    so that no flag of the process changes: the older fusion emitters
    (``{"xla_cpu_use_fusion_emitters": False}``, see the module docstring). Empty
    where ``XLA_FLAGS`` sets that option already (the user's choice, or the
    command's, wins) or the installed jaxlib predates the newer emitters. Read from
    the environment when called."""
    if PROGRAM_OPTION in os.environ.get("XLA_FLAGS", "") or _jaxlib_version() < FIRST_JAXLIB:
        return {}
    return {PROGRAM_OPTION: False}


def with_fast_cpu_compilation(xla_flags: str) -> str:
    """``xla_flags`` (the ``XLA_FLAGS`` value) with :data:`LEGACY_CPU_EMITTERS`
    added, unless it already sets that option (the user's choice wins) or the
    installed jaxlib predates the newer emitters."""
    if "xla_cpu_use_fusion_emitters" in xla_flags or _jaxlib_version() < FIRST_JAXLIB:
        return xla_flags
    return f"{xla_flags} {LEGACY_CPU_EMITTERS}".strip()


__all__ = ["LEGACY_CPU_EMITTERS", "PROGRAM_OPTION", "cpu_compiler_options", "with_fast_cpu_compilation"]
