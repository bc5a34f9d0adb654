"""The package version, from the installed distribution's metadata (one source: pyproject.toml)."""

from __future__ import annotations

import re
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("heliojax")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"


def release_tuple(text: str) -> tuple[int, ...]:
    """The leading numeric release parts of a version string: ``"0.9.1.dev3"`` ->
    ``(0, 9, 1)``, ``"1.0rc1"`` -> ``(1, 0)``, ``"0+unknown"`` -> ``(0,)``."""
    parts = []
    for piece in text.split("."):
        digits = re.match(r"\d+", piece)
        if digits is None:
            break
        parts.append(int(digits.group()))
        if digits.group() != piece:
            break
    return tuple(parts)
