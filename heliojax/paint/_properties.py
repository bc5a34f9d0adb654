"""Heliostat properties files (``<H>/Properties/<H>-heliostat-properties.json``)."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from .._errors import DataError
from .._io import check_path_argument
from ._common import (
    ACTUATOR_KEYS,
    ACTUATOR_OPTIONAL,
    ACTUATOR_REQUIRED,
    ACTUATOR_TYPES,
    MAX_HELIOSTAT_SIZE_M,
    PROPERTIES_SUFFIX,
    Facet,
    HeliostatProperties,
    Vec3,
    _check,
    _join,
    _latlon_ok,
    _load_json,
    _Node,
    _roundtrip,
    _type_name,
    _write_json,
    actuator_problem,
)

# ======================================================================================
# Heliostat properties
# ======================================================================================


def _actuator_from_json(file: str, node: _Node, notes: list[tuple[str, str]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ACTUATOR_KEYS:
        if key not in ACTUATOR_REQUIRED and not node.has(key):
            continue
        value = node.get(key)
        if key in ACTUATOR_OPTIONAL and isinstance(value, float) and math.isnan(value):
            # PAINT writes a value its source table lacks as NaN (json.dump): an optional
            # key heliojax does not need is left out, not the heliostat
            notes.append((node.field(key), "not finite (NaN): optional, left out"))
            continue
        if key == "type_axis":
            # PAINT wrote the raw "LINEAR" until it lower-cased its strings (PAINT commit 2a7068d)
            out[key] = node.string(key).lower()
            _check(
                out[key] in ACTUATOR_TYPES,
                file,
                node.field(key),
                f"unsupported actuator type {out[key]!r} (heliojax models {', '.join(ACTUATOR_TYPES)})",
            )
        elif key in ("min_increment", "max_increment", "clockwise_axis_movement"):
            out[key] = node.integer(key)
        else:
            out[key] = node.number(key)
    problem = actuator_problem(out)
    if problem is not None:
        raise DataError(file, node.field(problem[0]), problem[1])
    return out


MIN_FACET_HALF_SIZE_M = 1e-3
"""A canting vector (half a facet's edge, m) shorter than this is no facet (a zero
vector has no direction: its normal would be NaN and its rays lost without a word)."""
MIN_CANTING_SINE = 0.1
"""The canting vectors of a facet span its rectangle: at an angle whose sine is below
this (under ~6 deg) they are (nearly) parallel and the facet has no normal."""


def _facet(file: str, fn: _Node) -> Facet:
    """One facet entry: its translation within :data:`MAX_HELIOSTAT_SIZE_M` of the
    heliostat's centre, canting vectors of at most that length and at least
    :data:`MIN_FACET_HALF_SIZE_M`, not parallel."""
    t, e, n = fn.vec3("translation_vector"), fn.vec3("canting_e"), fn.vec3("canting_n")
    for key, v in (("translation_vector", t), ("canting_e", e), ("canting_n", n)):
        size = math.hypot(*v)
        _check(
            size <= MAX_HELIOSTAT_SIZE_M,
            file,
            fn.field(key),
            f"{size:.4g} m long, more than {MAX_HELIOSTAT_SIZE_M:g} m: not within a heliostat",
        )
        if key != "translation_vector":
            _check(
                size >= MIN_FACET_HALF_SIZE_M,
                file,
                fn.field(key),
                f"{size:.4g} m long, less than {MIN_FACET_HALF_SIZE_M:g} m: no facet edge",
            )
    cross = (e[1] * n[2] - e[2] * n[1], e[2] * n[0] - e[0] * n[2], e[0] * n[1] - e[1] * n[0])
    sine = math.hypot(*cross) / (math.hypot(*e) * math.hypot(*n))
    _check(
        sine >= MIN_CANTING_SINE,
        file,
        fn.field("canting_n"),
        f"(nearly) parallel to canting_e (sine of the angle {sine:.3g}): the facet has no normal",
    )
    return Facet(t, e, n)


MAX_FACET_OVERLAP = 0.1
"""Largest part of the smaller facet's area that two facets may share in the mirror plane
(PAINT's facets do not overlap; a facet listed twice, or at another's place, shares all of
it and would reflect its light twice)."""
MAX_FACET_AREA_RATIO = 1.25
"""Largest ratio of the facets' total area to the heliostat's ``width * height``
(PAINT's facets cover 99.3 % of it): above it the load report flags the facets, since
either they or the declared size are wrong."""


def _norm(v: Vec3) -> float:
    return math.hypot(*v)


def _facet_area(f: Facet) -> float:
    """Area (m^2) of the rectangle spanned by twice the canting vectors."""
    e, n = f.canting_e, f.canting_n
    cross = (e[1] * n[2] - e[2] * n[1], e[2] * n[0] - e[0] * n[2], e[0] * n[1] - e[1] * n[0])
    return 4.0 * _norm(cross)


def _overlap_fractions(facets: tuple[Facet, ...], j: int) -> np.ndarray:
    """Part of the smaller facet's area that facet ``j`` shares with each of the facets
    before it, measured in the earlier facet's edge directions (facets nearly in one
    plane, edges nearly parallel: PAINT's)."""
    t = np.array([f.translation_vector for f in facets[: j + 1]], float)
    d = t[j] - t[:j]
    shared = np.ones(j)
    for key in ("canting_e", "canting_n"):
        u = np.array([getattr(f, key) for f in facets[:j]], float).reshape(j, 3)
        length = np.linalg.norm(u, axis=1)
        other = math.hypot(*getattr(facets[j], key))
        along = np.abs(np.sum(d * u, axis=1)) / length
        shared *= np.maximum(0.0, np.minimum(length + other - along, 2.0 * np.minimum(length, other)))
    areas = np.array([_facet_area(f) for f in facets[:j]])
    return shared / np.minimum(areas, _facet_area(facets[j]))


def _check_facet_layout(file: str, field: str, facets: tuple[Facet, ...]) -> None:
    """No two facets at one place (:data:`MAX_FACET_OVERLAP`)."""
    for j in range(1, len(facets)):
        shared = _overlap_fractions(facets, j)
        i = int(np.argmax(shared))
        _check(
            not shared[i] > MAX_FACET_OVERLAP,
            file,
            f"{_join(field, j)}.translation_vector",
            f"{list(facets[j].translation_vector)}: the facet overlaps facet {i} (at "
            f"{list(facets[i].translation_vector)}) by {100 * shared[i]:.0f} % of its area (at most "
            f"{100 * MAX_FACET_OVERLAP:g} %): a facet listed twice or at another's place would reflect its light twice",
        )


def _facets_from_json(file: str, root: _Node) -> tuple[tuple[Facet, ...], str | None]:
    facets: tuple[Facet, ...] = ()
    canting_type = None
    if root.has("facet_properties"):
        fp = root.node("facet_properties")
        if fp.has("canting_type"):
            canting_type = fp.string("canting_type")
        raw = fp.get("facets")
        if not isinstance(raw, list):
            raise DataError(file, fp.field("facets"), f"expected an array, got {_type_name(raw)}")
        fl = []
        for i, fd in enumerate(raw):
            fn = _Node(file, fd, _join(fp.field("facets"), i))
            fl.append(_facet(file, fn))
        facets = tuple(fl)
        if fp.has("number_of_facets"):
            n = fp.integer("number_of_facets")
            _check(
                n == len(facets), file, fp.field("number_of_facets"), f"says {n} but {len(facets)} facets are listed"
            )
        _check_facet_layout(file, fp.field("facets"), facets)
    return facets, canting_type


def read_facets(path: str | os.PathLike) -> tuple[Facet, ...]:
    """Only ``facet_properties.facets`` of a heliostat-properties JSON (facet
    translations and canting vectors, m, heliostat surface frame), validated.

    Raises:
        DataError: naming the file and field; also when there are no facets.
    """
    file = str(path)
    facets, _ = _facets_from_json(file, _Node(file, _load_json(path)))
    if not facets:
        raise DataError(file, "facet_properties.facets", "missing or empty")
    return facets


def _offset_in_heliostat(file: str, kin: _Node, fmt: str) -> Vec3:
    """The (east, north, up) offset of the fields ``fmt`` formatted with e, n, u, in
    metres, each checked to lie within a heliostat."""
    out = []
    for c in "enu":
        v = float(kin.number(fmt.format(c)))
        _check(
            abs(v) <= MAX_HELIOSTAT_SIZE_M,
            file,
            kin.field(fmt.format(c)),
            f"{v!r} m is more than {MAX_HELIOSTAT_SIZE_M:g} m: not an offset within a heliostat",
        )
        out.append(v)
    return tuple(out)  # type: ignore[return-value]


SOUTH: Vec3 = (0.0, -1.0, 0.0)
"""The reference pose's ``initial_orientation`` (the mirror normal at zero joint angles
faces south), the one heliojax's kinematics assume."""
UP: Vec3 = (0.0, 0.0, 1.0)
"""PAINT's label of that same reference pose from 2024-12-06 (PAINT commit f1fc4bf) to
2025-11-28 (commit 6cad13e relabelled it; ARTIST's tutorial copies of one heliostat's
properties file before and after differ in nothing else)."""
OLDER_UP_LABEL = (
    "[0, 0, 1]: PAINT's label of the same reference pose from 2024-12 to 2025-11 "
    "(PAINT commit 6cad13e relabelled it [0, -1, 0]), read as south [0, -1, 0]"
)
KINEMATICS_KEY = "kinematics_properties"
OLDER_KINEMATICS_KEY = "kinematic_properties"
"""PAINT's key for the kinematics before version 3.0 (PAINT commit e644ef5, 2026-03)."""


UNIT_TOLERANCE = 1e-6
"""Largest deviation of ``initial_orientation``'s length from 1 read without a flag (PAINT
writes the direction's components exactly)."""


def _is(unit: tuple[float, ...], direction: Vec3) -> bool:
    return all(abs(a - b) < 1e-9 for a, b in zip(unit, direction, strict=True))


def _properties_from_json(file: str, data: Any, heliostat_id: str) -> HeliostatProperties:
    root = _Node(file, data)
    pos = root.vec3("heliostat_position")
    _latlon_ok(file, "heliostat_position", pos)
    width = float(root.number("width"))
    height = float(root.number("height"))
    _check(width > 0, file, "width", f"must be positive, got {width!r}")
    _check(height > 0, file, "height", f"must be positive, got {height!r}")
    for key, v in (("width", width), ("height", height)):
        _check(v <= MAX_HELIOSTAT_SIZE_M, file, key, f"{v!r} m is more than {MAX_HELIOSTAT_SIZE_M:g} m: no heliostat")
    notes: list[tuple[str, str]] = []
    orient = root.vec3("initial_orientation")
    norm = math.sqrt(sum(x * x for x in orient))
    _check(norm > 0, file, "initial_orientation", "zero vector")
    unit = tuple(x / norm for x in orient)
    if abs(norm - 1.0) > UNIT_TOLERANCE and (_is(unit, UP) or _is(unit, SOUTH)):
        notes.append(("initial_orientation", f"{list(orient)} has length {norm:g}, not 1: read as its direction"))
        orient = SOUTH if _is(unit, SOUTH) else orient
    if _is(unit, UP):
        notes.append(("initial_orientation", OLDER_UP_LABEL))
        orient = SOUTH
    _check(
        _is(unit, SOUTH) or _is(unit, UP),
        file,
        "initial_orientation",
        f"{list(orient)} is not south [0, -1, 0], the reference pose heliojax's kinematics assume",
    )
    kin_key = KINEMATICS_KEY
    if not root.has(KINEMATICS_KEY) and root.has(OLDER_KINEMATICS_KEY):
        kin_key = OLDER_KINEMATICS_KEY
        notes.append((kin_key, f"PAINT's key before version 3.0 (PAINT commit e644ef5), read as {KINEMATICS_KEY}"))
    kin = root.node(kin_key)
    acts = kin.get("actuators")
    if not isinstance(acts, list) or len(acts) != 2:
        what = f"an array of {len(acts)}" if isinstance(acts, list) else _type_name(acts)
        raise DataError(file, kin.field("actuators"), f"expected an array of 2 actuators, got {what}")
    actuators = tuple(
        _actuator_from_json(file, _Node(file, a, _join(kin.field("actuators"), i)), notes) for i, a in enumerate(acts)
    )

    joint_keys = ("joint_translation_{}_1", "joint_translation_{}_2")
    if not kin.has("joint_translation_e_1") and kin.has("first_joint_translation_e"):
        joint_keys = ("first_joint_translation_{}", "second_joint_translation_{}")
        notes.append(
            (
                kin.field("first_joint_translation_e"),
                "PAINT's joint translation keys before 2024-12-05 (PAINT commit 3bd4c37), read as "
                "joint_translation_<e|n|u>_<1|2>; PAINT wrote those files with concentrator_translation_n "
                "and _u swapped, which the calibration's tilts absorb only in part",
            )
        )
    jt1 = _offset_in_heliostat(file, kin, joint_keys[0])
    jt2 = _offset_in_heliostat(file, kin, joint_keys[1])
    conc = _offset_in_heliostat(file, kin, "concentrator_translation_{}")
    facets, canting_type = _facets_from_json(file, root)
    area = sum(_facet_area(f) for f in facets)
    if not area <= MAX_FACET_AREA_RATIO * width * height:  # flagged: the size or the facets may be the damaged field
        notes.append(
            (
                "facet_properties.facets",
                f"{len(facets)} facets of {area:.4g} m^2 in all do not fit the heliostat's width x height "
                f"{width:.4g} m x {height:.4g} m = {width * height:.4g} m^2 (at most {MAX_FACET_AREA_RATIO:g} "
                "times that): either the size or the facets are wrong (the flux is traced from the facets)",
            )
        )
    renovation = None
    if root.has("renovation") and root.get("renovation") is not None:
        renovation = root.string("renovation")
    return HeliostatProperties(
        heliostat_id=heliostat_id,
        position_lla=pos,
        width=width,
        height=height,
        initial_orientation=orient,
        actuators=actuators,  # type: ignore[arg-type]
        joint_translation_1=jt1,
        joint_translation_2=jt2,
        concentrator_translation=conc,
        facets=facets,
        canting_type=canting_type,
        renovation=renovation,
        source=file,
        notes=tuple(notes),
    )


def _properties_to_json(p: HeliostatProperties) -> dict:
    kin: dict[str, Any] = {"actuators": [{k: a[k] for k in ACTUATOR_KEYS if k in a} for a in p.actuators]}
    for name, vec in (
        ("joint_translation_{}_1", p.joint_translation_1),
        ("joint_translation_{}_2", p.joint_translation_2),
        ("concentrator_translation_{}", p.concentrator_translation),
    ):
        for c, x in zip("enu", vec):
            kin[name.format(c)] = x
    out: dict[str, Any] = {
        "heliostat_position": list(p.position_lla),
        "height": p.height,
        "width": p.width,
        "initial_orientation": list(p.initial_orientation),
        "kinematics_properties": kin,
    }
    if p.facets or p.canting_type is not None:
        fp: dict[str, Any] = {}
        if p.canting_type is not None:
            fp["canting_type"] = p.canting_type
        fp["number_of_facets"] = len(p.facets)
        fp["facets"] = [
            {
                "translation_vector": list(f.translation_vector),
                "canting_e": list(f.canting_e),
                "canting_n": list(f.canting_n),
            }
            for f in p.facets
        ]
        out["facet_properties"] = fp
    if p.renovation is not None:
        out["renovation"] = p.renovation
    return out


def _heliostat_id_from_properties_name(path: Path) -> str:
    name = path.name
    if not name.endswith(PROPERTIES_SUFFIX) or len(name) == len(PROPERTIES_SUFFIX):
        raise DataError(path, None, f"file name is not '<H>{PROPERTIES_SUFFIX}'")
    return name[: -len(PROPERTIES_SUFFIX)]


def read_heliostat_properties(path: str | os.PathLike, *, heliostat_id: str | None = None) -> HeliostatProperties:
    """Read and validate a ``<H>-heliostat-properties.json``.

    Args:
        path: the file.
        heliostat_id: overrides the id taken from the file name.

    Raises:
        TypeError, ValueError: ``path`` is no path or empty
            (:func:`heliojax._io.check_path_argument`).
        DataError: naming the file and the dotted field (e.g.
            ``kinematics_properties.actuators[0].increment``). The actuators must be
            ``linear`` with positive ``increment``, ``offset``, ``pivot_radius``,
            ``min_increment < max_increment`` and ``clockwise_axis_movement`` in {0, 1};
            ``initial_orientation`` must be south.
    """
    check_path_argument(path)
    path = Path(path)
    hid = heliostat_id if heliostat_id is not None else _heliostat_id_from_properties_name(path)
    return _properties_from_json(str(path), _load_json(path), hid)


def write_heliostat_properties(path: str | os.PathLike, properties: HeliostatProperties) -> None:
    """Write a heliostat-properties file (atomically)."""
    _write_json(path, _properties_to_json(properties))


def validate_properties(properties: HeliostatProperties) -> HeliostatProperties:
    """Run the reader's checks on an in-memory :class:`HeliostatProperties`
    (serialise and re-parse); returns the re-parsed (equal) value.

    Raises:
        DataError: as :func:`read_heliostat_properties`, with ``properties.source``
            as the file.
    """
    try:
        data = _roundtrip(_properties_to_json(properties))
    except (TypeError, ValueError) as e:
        raise DataError(properties.source, None, f"not serialisable: {e}") from None
    return _properties_from_json(properties.source, data, properties.heliostat_id)
