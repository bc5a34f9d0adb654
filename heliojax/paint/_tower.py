"""The tower file (``<PLANT>-tower-measurements.json``): plant reference point, targets, receiver."""

from __future__ import annotations

import logging
import math
import os
from typing import Any

import numpy as np

from .._errors import DataError
from .._io import shown_value
from .._limits import target_name_problem
from ._common import (
    CORNERS,
    TargetEntry,
    TowerFile,
    _latlon_ok,
    _load_json,
    _Node,
    _number,
    _type_name,
    _vec3,
    _write_json,
)

log = logging.getLogger(__name__)

# ======================================================================================
# Tower file
# ======================================================================================


MIN_TARGET_SIZE_M = 1e-3
"""A target narrower or lower than this (between the means of its opposite corners) has
no area: its corners coincide."""
MAX_TARGET_NORMAL_GAP_DEG = 45.0
"""A target's corners (left to right, lower to upper, as PAINT names them) span a plane
whose normal lies within this of the entry's ``normal_vector``: farther, two corners
are swapped (the target mirrored or turned, every spot on it misplaced)."""


def check_target_corners(
    source: str | os.PathLike, field: str, ul: Any, ur: Any, ll: Any, lr: Any, *, normal: Any = None
) -> None:
    """DataError (``source``, ``field``) unless the ENU corner points (m) upper left,
    upper right, lower left, lower right make a target: at least
    :data:`MIN_TARGET_SIZE_M` wide and high, opposite edges within a factor 2 of each
    other (a rectangle, no corner misplaced), the upper corners above the lower ones and,
    when ``normal`` (ENU) is given, facing within :data:`MAX_TARGET_NORMAL_GAP_DEG` of it."""
    ul, ur, ll, lr = (np.asarray(c, np.float64) for c in (ul, ur, ll, lr))
    u = (ur + lr) / 2 - (ul + ll) / 2  # left to right
    v = (ul + ur) / 2 - (ll + lr) / 2  # lower to upper
    width, height = float(np.linalg.norm(u)), float(np.linalg.norm(v))
    if not (width > MIN_TARGET_SIZE_M and height > MIN_TARGET_SIZE_M):
        raise DataError(source, field, f"degenerate target corners (width {width:.3g} m, height {height:.3g} m)")
    for side, a, b in (("upper", ul - ur, ll - lr), ("left", ul - ll, ur - lr)):
        la, lb = np.linalg.norm(a), np.linalg.norm(b)
        if max(la, lb) > 2.0 * min(la, lb):  # a rectangle's opposite edges are equal
            other = {"upper": "lower", "left": "right"}[side]
            raise DataError(
                source,
                field,
                f"the corners are no rectangle: the {side} edge is {la:.4g} m long, the {other} edge "
                f"{lb:.4g} m (one corner misplaced)",
            )
    if not v[2] > 0.0:
        raise DataError(source, field, f"the upper corners lie {-v[2]:.3g} m below the lower ones (corners swapped)")
    if normal is None:
        return
    n = np.cross(u, v)
    m = np.asarray(normal, np.float64)
    m = m / np.max(np.abs(m))  # its direction only: [0, 1e-300, 0]'s norm underflowed to 0, 1e300's overflowed
    cosine = float(np.dot(n, m) / (np.linalg.norm(n) * np.linalg.norm(m)))
    gap = math.degrees(math.acos(min(1.0, max(-1.0, cosine))))
    if gap > MAX_TARGET_NORMAL_GAP_DEG:
        raise DataError(
            source,
            field,
            f"the corners face {gap:.3g} deg away from normal_vector {list(normal)} (left and right, or "
            f"upper and lower, corners swapped)",
        )


def _tower_from_json(file: str, data: Any) -> TowerFile:
    root = _Node(file, data)
    plant = root.node("power_plant_properties")
    plant_id = plant.get("ID") if plant.has("ID") else ""
    if not isinstance(plant_id, (str, int)) or isinstance(plant_id, bool):
        raise DataError(file, plant.field("ID"), f"expected a string, got {_type_name(plant_id)}")
    origin = plant.vec3("coordinates")
    _latlon_ok(file, plant.field("coordinates"), origin)
    targets: dict[str, TargetEntry] = {}
    skipped: dict[str, str] = {}
    for name, value in root.data.items():
        if name == "power_plant_properties":
            continue
        problem = target_name_problem(name)
        if problem is not None:  # before its content is read: one bad name spoils no other target
            skipped[name] = problem
            continue
        entry = _Node(file, value, name)
        ttype = entry.string("type")
        normal = entry.vec3("normal_vector") if entry.has("normal_vector") else None
        coords = entry.node("coordinates")
        points = {str(k): _vec3(file, coords.field(k), v) for k, v in coords.data.items()}
        for k, p in points.items():
            _latlon_ok(file, coords.field(k), p)
        extra = {}
        for k, v in entry.data.items():
            if k in ("type", "normal_vector", "coordinates"):
                continue
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                v = _number(file, entry.field(k), v)
            elif not (v is None or isinstance(v, (str, bool))):
                raise DataError(file, entry.field(k), f"expected a scalar, got {_type_name(v)}")
            extra[k] = v
        if ttype == "planar":
            for c in CORNERS:
                if c not in points:
                    raise DataError(file, coords.field(c), "missing (a planar target needs four corners)")
            if normal is None:  # the corners alone face either way: left and right swapped went unseen
                raise DataError(
                    file, entry.field("normal_vector"), "missing (a planar target's left and right corners need it)"
                )
            if math.hypot(*normal) == 0.0:
                raise DataError(file, entry.field("normal_vector"), "zero vector")
        targets[name] = TargetEntry(name=name, type=ttype, normal=normal, points=points, extra=extra)
    tower = TowerFile(plant_id=str(plant_id), origin_lla=origin, targets=targets, source=file, skipped=skipped)
    if not tower.planar_target_names:
        more = f" (skipped by name: {', '.join(shown_value(n) for n in skipped)})" if skipped else ""
        raise DataError(file, None, f"no planar calibration target{more}")
    return tower


def skipped_target_message(tower: TowerFile, name: str) -> str | None:
    """Why ``tower`` has no target ``name``, when the loader skipped one of that name
    (:attr:`TowerFile.skipped`), or None."""
    problem = tower.skipped.get(name)
    if problem is None:
        return None
    return f"the tower file's target of that name was skipped (not a target name: {problem})"


def _tower_to_json(tower: TowerFile) -> dict:
    out: dict[str, Any] = {"power_plant_properties": {"ID": tower.plant_id, "coordinates": list(tower.origin_lla)}}
    for name, t in tower.targets.items():
        entry: dict[str, Any] = {"type": t.type}
        if t.normal is not None:
            entry["normal_vector"] = list(t.normal)
        entry.update(t.extra)
        entry["coordinates"] = {k: list(p) for k, p in t.points.items()}
        out[name] = entry
    return out


def read_tower(path: str | os.PathLike) -> TowerFile:
    """Read and validate a ``<PLANT>-tower-measurements.json``.

    Every entry besides ``power_plant_properties`` is kept (the receiver too);
    ``planar`` entries must carry the four corners ``upper_left``,
    ``upper_right``, ``lower_left``, ``lower_right`` and a ``normal_vector``, and are
    the calibration targets (:attr:`TowerFile.planar_target_names`).

    An entry whose name is no target name (:func:`heliojax._limits.target_name_problem`:
    blank, padded, multi-line, over 255 characters, or starting with ``= + - @``, a
    formula once written into a CSV cell) is skipped, unread, with a logged warning
    naming the file and the name, and listed in :attr:`TowerFile.skipped`; a record
    that names it is then skipped as one of an unknown target.

    Raises:
        DataError: naming the file and the field.
    """
    file = str(path)
    tower = _tower_from_json(file, _load_json(path))
    for name, problem in tower.skipped.items():
        log.warning(f"{file}: skipped target {shown_value(name)}: not a target name ({problem})")
    return tower


def write_tower(path: str | os.PathLike, tower: TowerFile) -> None:
    """Write ``tower`` as a PAINT tower file (atomically); DataError for a target whose
    name :func:`read_tower` would skip (:func:`heliojax._limits.target_name_problem`)."""
    for name in tower.targets:
        if (problem := target_name_problem(name)) is not None:
            raise DataError(path, shown_value(name), f"not a target name ({problem})")
    _write_json(path, _tower_to_json(tower))
