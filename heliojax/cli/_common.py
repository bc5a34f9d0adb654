"""Shared helpers of the CLI subcommands."""

from __future__ import annotations

import os
import sys
from pathlib import Path


def add_fit_arguments(p) -> None:
    """``--start`` and ``--cache-dir``, shared by the commands that fit."""
    p.add_argument(
        "--start",
        choices=("auto", "nominal"),
        default="auto",
        help="start geometry: per heliostat the better of nominal / fleet-typical actuators",
    )
    p.add_argument(
        "--cache-dir",
        default=None,
        help="persistent JAX compilation cache (default ~/.cache/heliojax/jax; 'none' disables)",
    )


def add_data_argument(p) -> None:
    p.add_argument(
        "data_dir",
        nargs="?",
        type=Path,
        default=None,
        metavar="DATA_DIR",
        help="PAINT-layout directory (default: the embedded real subset of PAINT)",
    )
    p.add_argument(
        "--centroid",
        choices=("utis", "helios"),
        default="utis",
        help="focal-spot centroid: UTIS with HeliOS fallback (default) or HeliOS only",
    )


def load_fleet(args):
    from ..paint import default_data_dir, load_paint_directory

    path = args.data_dir if args.data_dir is not None else default_data_dir()
    return load_paint_directory(path, centroid=args.centroid)


def progress(msg: str) -> None:
    print(f"[heliojax] {msg}", file=sys.stderr, flush=True)


def enable_compilation_cache(cache_dir: str | os.PathLike | None) -> None:
    """Persistent JAX compilation cache so a rerun does not recompile.

    ``cache_dir``: a directory, or None for ``$HELIOJAX_CACHE_DIR`` or
    ``~/.cache/heliojax/jax``; the string ``"none"`` disables it.
    """
    import jax

    if cache_dir is not None and str(cache_dir).lower() == "none":
        return
    path = Path(cache_dir or os.environ.get("HELIOJAX_CACHE_DIR") or Path.home() / ".cache" / "heliojax" / "jax")
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # keep small programs too
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
