"""PAINT deflectometry HDF5 files (groups ``facet1..facetN`` with ``surface_points``
and ``surface_normals``, metres, heliostat surface frame)."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence

import h5py
import numpy as np
from numpy.typing import ArrayLike

from .._errors import DataError
from .._io import atomic_h5

_FACET_GROUP = re.compile(r"^facet(\d+)\Z")


def read_deflectometry_facets(path: str | os.PathLike) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per facet ``(points (n_i, 3), unit normals (n_i, 3))`` float64 of a PAINT
    deflectometry file, in facet order.

    Raises:
        DataError: unreadable file, no facet groups, bad shapes or non-finite values.
    """
    facets = []
    try:
        with h5py.File(path, "r") as f:
            numbered = {int(m.group(1)): k for k in f.keys() if (m := _FACET_GROUP.match(k))}
            names = [numbered[i] for i in sorted(numbered)]
            if not names:
                raise DataError(path, None, "no facet groups (facet1..facetN)")
            for name in names:
                g = f[name]
                if not isinstance(g, h5py.Group):
                    raise DataError(path, name, "not a group")
                for field in ("surface_points", "surface_normals"):
                    if field not in g:
                        raise DataError(path, f"{name}/{field}", "missing")
                p = np.asarray(g["surface_points"], np.float64)
                q = np.asarray(g["surface_normals"], np.float64)
                if p.ndim != 2 or p.shape[1] != 3 or q.shape != p.shape or len(p) == 0:
                    raise DataError(path, f"{name}", f"expected matching [N, 3] arrays, got {p.shape} and {q.shape}")
                if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
                    raise DataError(path, f"{name}", "non-finite values")
                length = np.linalg.norm(q, axis=1, keepdims=True)
                if not np.all(length > 0):
                    row = int(np.flatnonzero(~(length[:, 0] > 0))[0])
                    raise DataError(path, f"{name}/surface_normals", f"row {row} is a zero vector: no direction")
                facets.append((p, q / length))
    except OSError as e:
        raise DataError(path, None, f"cannot read HDF5: {e}") from e
    return facets


def write_deflectometry(path: str | os.PathLike, facets: Sequence[tuple[ArrayLike, ArrayLike]]) -> None:
    """Write per-facet ``(points [n_i, 3], normals [n_i, 3])`` in PAINT's layout (float32), atomically."""
    with atomic_h5(path) as f:
        for i, (p, q) in enumerate(facets, start=1):
            g = f.create_group(f"facet{i}")
            g.create_dataset("surface_points", data=np.asarray(p, np.float32))
            g.create_dataset("surface_normals", data=np.asarray(q, np.float32))


__all__ = ["read_deflectometry_facets", "write_deflectometry"]
