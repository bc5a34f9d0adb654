"""ARTIST scenario HDF5 files (ARTIST 2.0 layout), read into and written from plain
records.

Layout (what ARTIST's scenario generator writes; ``[4]`` vectors are homogeneous,
``w = 1`` for points, ``0`` for directions)::

    power_plant/position                       [3] WGS84 lat_deg, lon_deg, alt_m
    heliostats/<H>/id, position [4]            ENU m about power_plant/position
    heliostats/<H>/kinematics/type             b"rigid_body"
    heliostats/<H>/kinematics/initial_orientation [4]
    heliostats/<H>/kinematics/deviations/<name> scalar (m or rad)
    heliostats/<H>/actuator/actuator_<i>/{type, clockwise_axis_movement,
        min_max_motor_positions [2], parameters/{increment, initial_angle,
        initial_stroke_length, offset, pivot_radius}}
    heliostats/<H>/surface/facets/facet_<k>/{position [4], canting [2, 4],
        control_points [nu, nv, 3], degrees [2]}
    prototypes/{kinematics, actuator, surface}  same groups, no id/position
    target_areas_planar/<T>/{position_center [4], normal_vector [1, 4], plane_e, plane_u}
    target_areas_cylindrical/<T>/<name>         kept as they are
    lightsources/<S>/{type, number_of_rays, distribution_parameters/{distribution_type, mean, covariance}}

The numbers are kept in the file's units; the mapping to heliojax's objects is
:mod:`heliojax.optics` (:func:`heliojax.optics.scene_from_artist`).
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping
from typing import Any

import h5py
import numpy as np

from .._errors import DataError
from .._io import H5_OUTSIDE_DATA_REFUSED, atomic_h5, h5_outside_data
from ._common import MAX_COUNTS, MAX_HELIOSTAT_DISTANCE_M
from ._properties import MIN_CANTING_SINE, MIN_FACET_HALF_SIZE_M

ACTUATOR_PARAMETERS = ("increment", "initial_angle", "initial_stroke_length", "offset", "pivot_radius")
"""Parameters of an ARTIST actuator (m, rad; ``increment`` counts per metre)."""

DEVIATIONS = (
    "first_joint_translation_e",
    "first_joint_translation_n",
    "first_joint_translation_u",
    "first_joint_tilt_n",
    "first_joint_tilt_u",
    "second_joint_translation_e",
    "second_joint_translation_n",
    "second_joint_translation_u",
    "second_joint_tilt_e",
    "second_joint_tilt_n",
    "concentrator_translation_e",
    "concentrator_translation_n",
    "concentrator_translation_u",
)
"""Kinematic deviations of ARTIST's rigid-body kinematics (m for translations, rad for tilts)."""

MAX_CONTROL_POINT_REACH = 2.0
"""Farthest a facet's NURBS control point may lie from the facet's centre, in units of
the facet's half-diagonal (``sqrt(|canting_e|^2 + |canting_n|^2)``, its centre-to-corner
distance). The control net of a clamped NURBS patch spans its facet: the corner control
points are the facet's corners, the others lie between them, so none is farther than about
one half-diagonal (a little more with curvature). A point at twice that would put part of
the surface over a neighbouring facet or beyond the heliostat: not a mirror, but damaged
numbers (a flipped byte reads as metres or kilometres)."""

MAX_CONTROL_POINT_HEIGHT = 0.1
"""Farthest a facet's NURBS control point may lie off the facet's plane (the plane through
its centre spanned by ``canting_e`` and ``canting_n``), in units of its half-diagonal: a
height ``h`` over the centre-to-corner distance ``d`` means a mean slope of about ``h / d``
off the plane. A mirror facet departs from its plane by milliradians (slope errors of
1-3 mrad; a curvature for a focal length of tens of metres or more, ``d / 2f``, ~10 mrad),
so a slope of 0.1 rad (100 mrad) is ten times any of these: a surface that rises 10 % of
its size off its facet is not a mirror facet. (Chosen from this reasoning, not fitted to
data; the shared deflectometry scenarios stay below 0.005.)"""

POSITIVE_ACTUATOR_PARAMETERS = {"increment": "counts/m", "offset": "m", "pivot_radius": "m"}
"""Actuator parameters that must be positive (the actuator law divides by each), with
their units."""

MAX_NURBS_DEGREE = 10
"""Highest NURBS degree of a facet read (ARTIST's are 2 or 3)."""

_NUMBERED = re.compile(r"^(?:actuator|facet)_(\d+)\Z")


@dataclasses.dataclass(frozen=True)
class ArtistActuator:
    """One actuator: ``type`` (``"linear"`` or ``"ideal"``), ``clockwise_axis_movement``,
    ``min_max_motor_positions`` (counts) and ``parameters`` (see :data:`ACTUATOR_PARAMETERS`)."""

    type: str
    clockwise_axis_movement: bool
    min_max_motor_positions: tuple[int, int]
    parameters: Mapping[str, float]


@dataclasses.dataclass(frozen=True)
class ArtistFacet:
    """One facet: ``position`` ``(3,)`` m and ``canting`` ``(2, 3)`` (the ``e`` and ``n``
    half-edge vectors) in the heliostat's surface frame, ``control_points``
    ``(nu, nv, 3)`` m and the NURBS ``degrees`` ``(2,)``.

    ARTIST cants and translates the control points itself when every control
    point of the heliostat has ``z == 0`` (a flat facet, as in its "ideal"
    scenarios); otherwise they are already in the surface frame."""

    position: np.ndarray
    canting: np.ndarray
    control_points: np.ndarray
    degrees: tuple[int, int]


@dataclasses.dataclass(frozen=True)
class ArtistHeliostat:
    """One heliostat (or the prototype, with ``position`` and ``id`` ``None``)."""

    name: str
    id: int | None
    position: np.ndarray | None
    kinematics_type: str
    initial_orientation: np.ndarray
    deviations: Mapping[str, float]
    actuators: tuple[ArtistActuator, ...]
    facets: tuple[ArtistFacet, ...]


@dataclasses.dataclass(frozen=True)
class ArtistPlanarTarget:
    """A planar target area: ``centre`` ``(3,)`` ENU m, unit ``normal`` ``(3,)``, full
    ``width`` (along east, ``plane_e``) and ``height`` (``plane_u``), m."""

    centre: np.ndarray
    normal: np.ndarray
    width: float
    height: float


@dataclasses.dataclass(frozen=True)
class ArtistLightSource:
    """A light source: ``type`` (``"sun"``), ``number_of_rays``, ``distribution_type``
    (``"normal"``) with ``mean`` and ``covariance`` (rad^2 per axis)."""

    type: str
    number_of_rays: int
    distribution_type: str
    mean: float
    covariance: float


@dataclasses.dataclass(frozen=True)
class ArtistScenario:
    """The contents of an ARTIST scenario file (units of the file)."""

    source: str
    plant_position_lla: np.ndarray
    heliostats: tuple[ArtistHeliostat, ...]
    prototype: ArtistHeliostat | None
    planar_targets: Mapping[str, ArtistPlanarTarget]
    cylindrical_targets: Mapping[str, Mapping[str, np.ndarray]]
    light_sources: Mapping[str, ArtistLightSource]
    number_of_heliostat_groups: int | None = None
    version: float = 1.0
    skipped: tuple[tuple[str, str], ...] = ()
    """``(heliostat, reason)`` of each heliostat left out by ``skip_bad`` (:func:`read_artist_scenario`)."""


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


class _Reader:
    def __init__(self, path: str):
        self.path = path

    def fail(self, field: str, reason: str) -> DataError:
        return DataError(self.path, field, reason)

    @staticmethod
    def where(group: Any, name: str = "") -> str:
        return f"{(group.name or '').strip('/')}/{name}".strip("/")

    def node(self, group: Any, name: str) -> Any:
        if not isinstance(group, h5py.Group):
            raise self.fail(self.where(group), "is a dataset, expected a group")
        if name not in group:
            raise self.fail(self.where(group, name), "missing")
        try:
            obj = group[name]
        except (KeyError, RuntimeError, OSError, ValueError) as e:  # a dangling, external or looping link
            raise self.fail(self.where(group, name), f"cannot be read ({e})") from None
        outside = h5_outside_data(obj, group.file.filename)  # round 14: read another scenario's data
        if outside is not None:
            raise self.fail(self.where(group, name), H5_OUTSIDE_DATA_REFUSED.format(why=outside))
        return obj

    def group(self, parent: Any, name: str) -> Any:
        g = self.node(parent, name)
        if not isinstance(g, h5py.Group):
            raise self.fail(self.where(parent, name), "is a dataset, expected a group")
        return g

    def groups(self, parent: Any) -> list[tuple[str, Any]]:
        """Every entry of ``parent`` (a group each), in the file's order."""
        return [(k, self.group(parent, k)) for k in parent]

    def dataset(self, group: Any, name: str) -> Any:
        obj = self.node(group, name)
        if not isinstance(obj, h5py.Dataset):
            raise self.fail(self.where(group, name), "is a group, expected a dataset")
        try:
            return obj[()]
        except (OSError, RuntimeError, ValueError, TypeError) as e:  # damaged chunks, an unknown type
            raise self.fail(self.where(group, name), f"cannot be read ({e})") from None

    def array(self, group: Any, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
        field = self.where(group, name)
        value = self.dataset(group, name)
        try:
            a = np.asarray(value, np.float64)
        except (TypeError, ValueError) as e:
            raise self.fail(field, f"not numeric ({e})") from None
        if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape, strict=True)):
            raise self.fail(field, f"shape {a.shape}, expected {tuple('*' if s is None else s for s in shape)}")
        if not np.all(np.isfinite(a)):
            raise self.fail(field, "non-finite value")
        return a

    def number(self, group: Any, name: str) -> float:
        return float(self.array(group, name, ()))

    def positive(self, group: Any, name: str, unit: str) -> float:
        value = self.number(group, name)
        if not value > 0.0:
            raise self.fail(self.where(group, name), f"{value:g} {unit}; expected > 0")
        return value

    def whole(self, group: Any, name: str, shape: tuple[int | None, ...], low: float, high: float) -> np.ndarray:
        """Whole numbers in ``[low, high]`` (a count, a degree, an id: 2.7 had been cut to 2)."""
        a = self.array(group, name, shape)
        bad = (a != np.round(a)) | (a < low) | (a > high)
        if bad.any():
            raise self.fail(
                self.where(group, name),
                f"{a[bad].reshape(-1)[0]:g}; expected a whole number in [{low:.0f}, {high:.0f}]",
            )
        return a.astype(np.int64)

    def flag(self, group: Any, name: str) -> bool:
        value = self.dataset(group, name)
        if isinstance(value, (bool, np.bool_)) or (isinstance(value, np.integer | int) and value in (0, 1)):
            return bool(value)
        shown = repr(value.item() if isinstance(value, np.generic) else value)
        shown = shown if np.ndim(value) == 0 else f"an array of shape {np.shape(value)}"
        raise self.fail(self.where(group, name), f"{shown}; expected a boolean (true/false or 0/1)")

    def text(self, group: Any, name: str) -> str:
        value = self.dataset(group, name)
        if isinstance(value, bytes):
            try:
                return value.decode()
            except UnicodeDecodeError:
                raise self.fail(self.where(group, name), f"{value[:40]!r}: not UTF-8 text") from None
        if isinstance(value, str):
            return value
        raise self.fail(self.where(group, name), f"expected a string, got {type(value).__name__}")

    def numbered(self, group: Any) -> list[str]:
        found = {int(m.group(1)): k for k in group if (m := _NUMBERED.match(k))}
        if not found:
            raise self.fail(self.where(group), "no numbered entries")
        return [found[i] for i in sorted(found)]

    def heliostat(self, g: Any, name: str, prototype: bool) -> ArtistHeliostat:
        kin = self.group(g, "kinematics")
        dev_group = self.group(kin, "deviations")
        deviations = {k: self.number(dev_group, k) for k in DEVIATIONS if k in dev_group}
        actuators = []
        act_group = self.group(g, "actuator")
        for a in self.numbered(act_group):
            ag = self.group(act_group, a)
            params = self.group(ag, "parameters")
            mm = self.whole(ag, "min_max_motor_positions", (2,), -MAX_COUNTS, MAX_COUNTS)
            if not mm[0] < mm[1]:
                raise self.fail(
                    self.where(ag, "min_max_motor_positions"), f"{mm.tolist()}: the minimum is not below the maximum"
                )
            actuators.append(
                ArtistActuator(
                    type=self.text(ag, "type"),
                    clockwise_axis_movement=self.flag(ag, "clockwise_axis_movement"),
                    min_max_motor_positions=(int(mm[0]), int(mm[1])),
                    parameters={
                        k: self.positive(params, k, POSITIVE_ACTUATOR_PARAMETERS[k])
                        if k in POSITIVE_ACTUATOR_PARAMETERS
                        else self.number(params, k)
                        for k in ACTUATOR_PARAMETERS
                    },
                )
            )
        if len(actuators) != 2:
            raise self.fail(self.where(act_group), f"{len(actuators)} actuators, expected 2")
        facets = []
        fg = self.group(self.group(g, "surface"), "facets")
        for k in self.numbered(fg):
            f = self.group(fg, k)
            deg = self.whole(f, "degrees", (2,), 1, MAX_NURBS_DEGREE)
            cp = self.array(f, "control_points", (None, None, 3))
            if cp.shape[0] <= deg[0] or cp.shape[1] <= deg[1]:
                raise self.fail(self.where(f, "control_points"), f"{cp.shape[:2]} too few for degrees {deg}")
            facets.append(
                ArtistFacet(
                    position=self.array(f, "position", (4,))[:3],
                    canting=self.array(f, "canting", (2, 4))[:, :3],
                    control_points=cp,
                    degrees=(int(deg[0]), int(deg[1])),
                )
            )
        self.check_control_points(fg, facets)
        position = None
        if not prototype:
            position = self.array(g, "position", (4,))[:3]
            if not np.linalg.norm(position) <= MAX_HELIOSTAT_DISTANCE_M:
                raise self.fail(
                    self.where(g, "position"),
                    f"{np.linalg.norm(position):.4g} m from the plant's origin, more than "
                    f"{MAX_HELIOSTAT_DISTANCE_M:g} m: not a heliostat of this plant (damaged numbers?)",
                )
        return ArtistHeliostat(
            name=name,
            id=None if prototype else int(self.whole(g, "id", (), 0, 2**63 - 1)),
            position=position,
            kinematics_type=self.text(kin, "type"),
            initial_orientation=self.array(kin, "initial_orientation", (4,))[:3],
            deviations=deviations,
            actuators=tuple(actuators),
            facets=tuple(facets),
        )

    def check_control_points(self, group: Any, facets: list[ArtistFacet]) -> None:
        """Refuse control points too far from their facet (:data:`MAX_CONTROL_POINT_REACH`)
        or off its plane (:data:`MAX_CONTROL_POINT_HEIGHT`). The points are facet-local
        and flat when every one of the heliostat is at ``z == 0`` (ARTIST then cants and
        translates them), else already canted and translated (centred on ``position``)."""
        flat = all(np.all(f.control_points[..., 2] == 0.0) for f in facets)
        for k, facet in zip(self.numbered(group), facets, strict=True):
            field = self.where(group[k], "control_points")
            e, n = facet.canting
            length_e, length_n = float(np.linalg.norm(e)), float(np.linalg.norm(n))
            half_diagonal = float(np.hypot(length_e, length_n))
            # each edge, as the optics' facet layout requires (one edge of zero length, or
            # two parallel ones, had passed the half-diagonal alone and made a facet of no area)
            sine = float(np.linalg.norm(np.cross(e, n))) / max(length_e * length_n, 1e-300)
            if not (min(length_e, length_n) >= MIN_FACET_HALF_SIZE_M and sine >= MIN_CANTING_SINE):
                raise self.fail(
                    self.where(group[k], "canting"),
                    f"half-edges of {length_e:.3g} and {length_n:.3g} m at an angle of sine {sine:.3g}: no facet "
                    f"(each half-edge at least {MIN_FACET_HALF_SIZE_M:g} m, sine at least {MIN_CANTING_SINE:g})",
                )
            local = facet.control_points - (0.0 if flat else facet.position)
            reach = float(np.linalg.norm(local, axis=-1).max())
            if reach > MAX_CONTROL_POINT_REACH * half_diagonal:
                raise self.fail(
                    field,
                    f"a control point {reach:.4g} m from the facet's centre, more than {MAX_CONTROL_POINT_REACH:g} "
                    f"times its half-diagonal ({half_diagonal:.3g} m): not on the facet (damaged numbers?)",
                )
            normal = np.asarray([0.0, 0.0, 1.0]) if flat else np.cross(e, n)
            if np.linalg.norm(normal) < 1e-12:  # canting half-edges parallel: no plane to measure from
                continue
            height = float(np.abs(local @ (normal / np.linalg.norm(normal))).max())
            if height > MAX_CONTROL_POINT_HEIGHT * half_diagonal:
                raise self.fail(
                    field,
                    f"a control point {height:.4g} m off the facet's plane, more than {MAX_CONTROL_POINT_HEIGHT:g} "
                    f"times its half-diagonal ({half_diagonal:.3g} m; a slope of 100 mrad): not a mirror facet "
                    "(damaged numbers?)",
                )

    def scenario(self, f: Any, skip_bad: bool = False) -> ArtistScenario:
        hel = self.group(f, "heliostats")
        read, skipped = [], []
        for k in hel:  # each read in its own try (round 14: a dangling or external link spoilt every one)
            try:
                read.append(self.heliostat(self.group(hel, k), k, False))
            except DataError as e:
                if not skip_bad:
                    raise
                skipped.append((k, str(e)))
        if not read:
            damaged = f" (every one damaged: {skipped[0][1]})" if skipped else ""
            raise self.fail("heliostats", "no heliostats" + damaged)
        heliostats: list[ArtistHeliostat] = []
        ids: dict[int | None, str] = {}
        for h in read:
            if h.id in ids:
                problem = self.fail(f"heliostats/{h.name}/id", f"{h.id}, the id of heliostats/{ids[h.id]} too")
                if not skip_bad:
                    raise problem
                skipped.append((h.name, str(problem)))
                continue
            ids[h.id] = h.name
            heliostats.append(h)
        prototype = self.heliostat(self.group(f, "prototypes"), "prototype", True) if "prototypes" in f else None
        planar = {}
        if "target_areas_planar" in f:
            for k, t in self.groups(self.group(f, "target_areas_planar")):
                normals = self.array(t, "normal_vector", (None, 4))
                normal = normals[0, :3] if len(normals) else np.zeros(3)
                if not np.linalg.norm(normal) > 0.0:
                    raise self.fail(self.where(t, "normal_vector"), f"{normals.tolist()}: no direction")
                planar[k] = ArtistPlanarTarget(
                    centre=self.array(t, "position_center", (4,))[:3],
                    normal=normal,
                    width=self.positive(t, "plane_e", "m"),
                    height=self.positive(t, "plane_u", "m"),
                )
        cylindrical = {}
        if "target_areas_cylindrical" in f:
            for k, t in self.groups(self.group(f, "target_areas_cylindrical")):
                cylindrical[k] = {n: np.asarray(self.dataset(t, n)) for n in t}
        lights = {}
        if "lightsources" in f:
            for k, s in self.groups(self.group(f, "lightsources")):
                d = self.group(s, "distribution_parameters")
                lights[k] = ArtistLightSource(
                    type=self.text(s, "type"),
                    number_of_rays=int(self.whole(s, "number_of_rays", (), 1, 2**31 - 1)),
                    distribution_type=self.text(d, "distribution_type"),
                    mean=self.number(d, "mean"),
                    covariance=self.number(d, "covariance"),
                )
        groups = None
        if "number_of_heliostat_groups" in f:
            groups = int(self.whole(f, "number_of_heliostat_groups", (), 1, len(heliostats)))
        plant = self.group(f, "power_plant")
        lla = self.array(plant, "position", (3,))
        if not (abs(lla[0]) <= 90.0 and abs(lla[1]) <= 360.0):
            raise self.fail(
                self.where(plant, "position"), f"latitude {lla[0]:g} deg, longitude {lla[1]:g} deg: not on the earth"
            )
        try:
            version = float(f.attrs.get("version", 1.0))
        except (TypeError, ValueError):
            raise self.fail("version (attribute)", f"{f.attrs['version']!r}: not a number") from None
        return ArtistScenario(
            source=self.path,
            plant_position_lla=lla,
            heliostats=tuple(heliostats),
            prototype=prototype,
            planar_targets=planar,
            cylindrical_targets=cylindrical,
            light_sources=lights,
            number_of_heliostat_groups=groups,
            version=version,
            skipped=tuple(skipped),
        )


def read_artist_scenario(path: str | os.PathLike, skip_bad: bool = False) -> ArtistScenario:
    """Read an ARTIST scenario HDF5 file.

    Args:
        path: the file.
        skip_bad: leave out a heliostat whose group is damaged (its reason in
            :attr:`ArtistScenario.skipped`) instead of refusing the file, so that one
            bad heliostat does not spoil the others.

    Raises:
        DataError: unreadable file, missing groups or datasets (named by their HDF5
            path), wrong shapes or non-finite numbers (with ``skip_bad``: outside the
            heliostats, or in every heliostat).
    """
    reader = _Reader(str(path))
    try:
        with h5py.File(path, "r") as f:
            return reader.scenario(f, skip_bad)
    except OSError as e:
        raise DataError(path, None, f"not a readable HDF5 file ({e})") from None


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _h(v, w: float) -> np.ndarray:
    return np.concatenate([np.asarray(v, np.float32).reshape(3), np.asarray([w], np.float32)])


def _write_heliostat(g: Any, h: ArtistHeliostat) -> None:
    if h.id is not None:
        g["id"] = np.int64(h.id)
    if h.position is not None:
        g["position"] = _h(h.position, 1.0)
    k = g.create_group("kinematics")
    k["type"] = np.bytes_(h.kinematics_type)
    k["initial_orientation"] = _h(h.initial_orientation, 0.0)
    d = k.create_group("deviations")
    for name, value in h.deviations.items():
        d[name] = np.float32(value)
    for i, a in enumerate(h.actuators):
        ag = g.create_group(f"actuator/actuator_{i}")
        ag["type"] = np.bytes_(a.type)
        ag["clockwise_axis_movement"] = np.bool_(a.clockwise_axis_movement)
        ag["min_max_motor_positions"] = np.asarray(a.min_max_motor_positions, np.int64)
        p = ag.create_group("parameters")
        for name, value in a.parameters.items():
            p[name] = np.float32(value)
    for i, facet in enumerate(h.facets, start=1):
        fg = g.create_group(f"surface/facets/facet_{i}")
        fg["position"] = _h(facet.position, 0.0)
        fg["canting"] = np.stack([_h(c, 0.0) for c in np.asarray(facet.canting)])
        fg["control_points"] = np.asarray(facet.control_points, np.float32)
        fg["degrees"] = np.asarray(facet.degrees, np.int64)


def write_artist_scenario(path: str | os.PathLike, scenario: ArtistScenario) -> None:
    """Write ``scenario`` in ARTIST's layout (float32 numbers, as ARTIST writes them),
    atomically."""
    with atomic_h5(path) as f:
        f.attrs["version"] = np.float64(scenario.version)
        f["power_plant/position"] = np.asarray(scenario.plant_position_lla, np.float64)
        if scenario.number_of_heliostat_groups is not None:
            f["number_of_heliostat_groups"] = np.int64(scenario.number_of_heliostat_groups)
        for h in scenario.heliostats:
            _write_heliostat(f.create_group(f"heliostats/{h.name}"), h)
        if scenario.prototype is not None:
            _write_heliostat(f.create_group("prototypes"), scenario.prototype)
        for name, t in scenario.planar_targets.items():
            g = f.create_group(f"target_areas_planar/{name}")
            g["position_center"] = _h(t.centre, 1.0)
            g["normal_vector"] = _h(t.normal, 0.0)[None]
            g["plane_e"] = np.float32(t.width)
            g["plane_u"] = np.float32(t.height)
        for name, entries in scenario.cylindrical_targets.items():
            g = f.create_group(f"target_areas_cylindrical/{name}")
            for k, v in entries.items():
                g[k] = v
        for name, s in scenario.light_sources.items():
            g = f.create_group(f"lightsources/{name}")
            g["type"] = np.bytes_(s.type)
            g["number_of_rays"] = np.int64(s.number_of_rays)
            g["distribution_parameters/distribution_type"] = np.bytes_(s.distribution_type)
            g["distribution_parameters/mean"] = np.float64(s.mean)
            g["distribution_parameters/covariance"] = np.float64(s.covariance)


__all__ = [
    "ACTUATOR_PARAMETERS",
    "DEVIATIONS",
    "ArtistActuator",
    "ArtistFacet",
    "ArtistHeliostat",
    "ArtistLightSource",
    "ArtistPlanarTarget",
    "ArtistScenario",
    "read_artist_scenario",
    "write_artist_scenario",
]
