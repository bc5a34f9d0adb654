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
``benchmarks/calibration_speed.py``, one run each on 2 cores). GPUs ignore the flag.
"""

from __future__ import annotations

import importlib.metadata
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


def with_fast_cpu_compilation(xla_flags: str) -> str:
    """``xla_flags`` (the ``XLA_FLAGS`` value) with :data:`LEGACY_CPU_EMITTERS`
    added, unless it already sets that option (the user's choice wins) or the
    installed jaxlib predates the newer emitters."""
    if "xla_cpu_use_fusion_emitters" in xla_flags or _jaxlib_version() < FIRST_JAXLIB:
        return xla_flags
    return f"{xla_flags} {LEGACY_CPU_EMITTERS}".strip()


__all__ = ["LEGACY_CPU_EMITTERS", "with_fast_cpu_compilation"]
