"""ARTIST scenarios <-> heliojax objects.

ARTIST (the PyTorch heliostat digital twin) stores a scene in one HDF5 file
(:mod:`heliojax.paint` reads and writes its layout). :func:`scene_from_artist`
turns it into heliojax's objects and :func:`scene_to_artist` writes heliojax's
(fitted) kinematics and surfaces back.

Mapping of conventions (read from ARTIST's source, checked against the numbers
of the shared scenarios and by a second implementation of ARTIST's chain in the
tests)
--------------------------------------------------------------------------------

* **Frames.** Both use local ENU metres. ARTIST's heliostat positions are ENU
  about ``power_plant/position``; they differ from heliojax's exact WGS84 -> ENU
  conversion of the same PAINT coordinates by < 0.6 mm (ARTIST's approximate
  conversion); heliojax keeps ARTIST's numbers. Facet positions, canting vectors
  and control points are in the same surface frame (mirror facing up, ``x`` east,
  ``y`` north; :mod:`heliojax._heliostat` maps it to the body frame by
  ``Rx(pi/2)``, ARTIST by its ``initial_orientation`` (0, -1, 0) offset, the same
  rotation).
* **Chain.** ARTIST's rigid body is
  ``T(P) Rn(t1n) Ru(t1u) T(V01) Re(theta - pi/2) Re(t2e) Rn(t2n) T(V12) Ru(tau) T(V2M)``
  with ARTIST's ``rotate_n(a) = Ry(-a)`` (opposite to a right-handed rotation
  about north), ``rotate_e = Rx``, ``rotate_u = Rz``; heliojax's is
  ``Ry(alpha) Rz(beta) Rx(theta - pi/2) Ry(gamma) Rz(tau) Rx(delta)``. Hence
  ``alpha = -first_joint_tilt_n``, ``beta = first_joint_tilt_u``,
  ``gamma = -second_joint_tilt_n``, and ``second_joint_tilt_e`` is an offset of
  axis 1's angle (added to ``angle_offset[0]``). heliojax's mirror tilt
  ``delta`` has **no ARTIST counterpart** (it acts after the axis-2 rotation);
  :func:`scene_to_artist` refuses a model with ``delta != 0`` unless told to
  drop it. The translations ``V01`` and ``V12`` are rotated by the preceding
  tilts in ARTIST but not in heliojax: a second-order difference (tilt x offset,
  0 for the PAINT heliostats, whose ``V01 = V12 = 0``).
* **Actuators.** ARTIST's linear actuator is heliojax's law of cosines with the
  same five parameters (``initial_angle`` in the file is PAINT's; ARTIST subtracts
  ``pi/2`` on axis 1 at load, as heliojax's chain does). heliojax's fitted
  ``angle_offset``, ``increment_scale`` and ``stroke_offset`` are written into
  ``initial_angle``, ``increment`` and ``initial_stroke_length`` (on ideal axes,
  an ``increment`` and ``initial_angle`` whose linearised law is the fitted
  linear map). An *ideal*
  ARTIST actuator takes motor positions *as* joint angles (rad), whereas
  heliojax's ideal axis maps PAINT's integer counts to angles by the linearised
  actuator law: the parameters are carried through unchanged, but motor
  positions mean different things in the two codes for such axes.
* **Surfaces.** ARTIST's NURBS have clamped uniform knots (as
  :class:`NurbsFacets`), unit weights, and control points spread uniformly over
  the facet (not on the Greville abscissae). When every control point of a
  heliostat has ``z == 0`` ARTIST cants each facet (rotation with columns
  ``e = unit(canting_e)``, ``u = unit(e x canting_n)``, ``n = u x e``) and
  translates it; otherwise the control points are already canted and
  translated. heliojax keeps facet-local (canted) control points and the facet
  translation; :func:`scene_to_artist` writes the flat form back when a
  heliostat's facets are its canted flat facets, else the translated form.
* **Targets.** ARTIST's planar target (centre, normal, ``plane_e`` and
  ``plane_u`` full widths) is a :class:`heliojax.TargetPlane` with ``v_axis`` the
  up direction made orthogonal to the normal and ``u_axis = v_axis x normal``
  (west for the north-facing Jülich targets, as heliojax's targets from the tower
  file). Cylindrical targets are carried through unchanged.
* **Sun.** ARTIST's ``normal`` light source with covariance ``s^2`` per axis is
  :class:`GaussianSun` ``(sigma = s)``.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._errors import DataError
from .._geometry import TargetPlane, normalize
from .._heliostat import HeliostatGeometry, LinearActuators
from .._kinematics import ActuatorModel
from ..paint import (
    ArtistActuator,
    ArtistFacet,
    ArtistHeliostat,
    ArtistLightSource,
    ArtistPlanarTarget,
    ArtistScenario,
    read_artist_scenario,
)
from ._nurbs import NurbsFacets
from ._sunshape import MAX_SPREAD_RAD, AbstractSunShape, GaussianSun
from ._surfaces import FacetLayout


@dataclasses.dataclass(frozen=True)
class Scene:
    """A heliostat scene in heliojax's objects (ENU m about ``origin_lla``, rad).

    Attributes:
        heliostat_ids: ``(h,)`` names.
        origin_lla: ``(3,)`` WGS84 lat_deg, lon_deg, alt_m of the ENU origin.
        geometry: :class:`heliojax.HeliostatGeometry` batched ``(h, ...)``.
        model: :class:`heliojax.ActuatorModel` batched ``(h, ...)`` holding the
            scenario's kinematic deviations (tilts; zero for PAINT's nominal geometry).
        layout: :class:`FacetLayout` ``(h, f, ...)``.
        facets: :class:`NurbsFacets` ``(h, f, nu, nv, 3)`` (facet-local, canted).
        targets: planar targets by name.
        sunshape: the light source as a sun shape.
        template: the scenario read (kept for what heliojax does not model:
            prototypes, cylindrical targets, ray counts), or ``None``.
    """

    heliostat_ids: tuple[str, ...]
    origin_lla: np.ndarray
    geometry: HeliostatGeometry
    model: ActuatorModel
    layout: FacetLayout
    facets: NurbsFacets
    targets: Mapping[str, TargetPlane]
    sunshape: AbstractSunShape
    template: ArtistScenario | None = None

    def index(self, heliostat_id: str) -> int:
        """Position of ``heliostat_id`` in the batch."""
        try:
            return self.heliostat_ids.index(heliostat_id)
        except ValueError:
            raise KeyError(f"{heliostat_id!r} is not in the scene ({', '.join(self.heliostat_ids)})") from None


def _canting_rotation(canting: np.ndarray) -> np.ndarray:
    """ARTIST's canting rotation ``(..., 3, 3)`` (columns ``e, n, u``) of ``(..., 2, 3)`` canting vectors."""
    e = canting[..., 0, :] / np.linalg.norm(canting[..., 0, :], axis=-1, keepdims=True)
    u = np.cross(e, canting[..., 1, :])
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    n = np.cross(u, e)
    return np.stack([e, n, u], axis=-1)


def _target(t: ArtistPlanarTarget, dtype) -> TargetPlane:
    normal = normalize(jnp.asarray(t.normal, dtype))
    up = jnp.asarray([0.0, 0.0, 1.0], dtype)
    v = normalize(up - jnp.dot(up, normal) * normal)
    return TargetPlane(
        centre=jnp.asarray(t.centre, dtype),
        normal=normal,
        u_axis=jnp.cross(v, normal),
        v_axis=v,
        half_width=jnp.asarray(t.width / 2.0, dtype),
        half_height=jnp.asarray(t.height / 2.0, dtype),
    )


@eqx.filter_jit
def _build_geometry(position, actuators, v01, v12, v2m, ideal_axes) -> HeliostatGeometry:
    """:meth:`HeliostatGeometry.build` (the actuator law's linearisation), compiled."""
    return HeliostatGeometry.build(position, actuators, v01, v12, v2m, ideal_axes=ideal_axes)


def scene_from_artist(scenario: ArtistScenario | str | os.PathLike, dtype=jnp.float64, skip_bad: bool = False) -> Scene:
    """An ARTIST scenario (file or :class:`heliojax.paint.ArtistScenario`) as a :class:`Scene`.

    Every heliostat must have the same number of facets and control points and
    one NURBS degree in both directions (as ARTIST's own scenarios do).

    Args:
        scenario: the file or its contents.
        dtype: the scene's float type.
        skip_bad: a file's damaged heliostats are left out (:func:`read_artist_scenario`;
            listed in its ``skipped``) instead of refusing the file.

    Raises:
        DataError: an unreadable file or one outside what heliojax models (naming
            the heliostat and field).
    """
    if not isinstance(scenario, ArtistScenario):
        scenario = read_artist_scenario(scenario, skip_bad=skip_bad)
    src = scenario.source
    hs = scenario.heliostats
    shapes = {(len(h.facets),) + f.control_points.shape + f.degrees for h in hs for f in h.facets}
    if len(shapes) != 1:
        raise DataError(
            src, "heliostats/*/surface/facets", f"facets differ in count, control points or degree: {shapes}"
        )
    degrees = hs[0].facets[0].degrees
    if degrees[0] != degrees[1]:
        raise DataError(src, f"heliostats/{hs[0].name}/surface/facets/facet_1/degrees", f"{degrees}: one degree needed")
    for h in hs:
        if h.kinematics_type != "rigid_body":
            raise DataError(
                src, f"heliostats/{h.name}/kinematics/type", f"{h.kinematics_type!r}, expected 'rigid_body'"
            )
        if not np.allclose(h.initial_orientation, (0.0, -1.0, 0.0)):
            raise DataError(src, f"heliostats/{h.name}/kinematics/initial_orientation", "only (0, -1, 0) is supported")
        for i, a in enumerate(h.actuators):
            if a.type not in ("linear", "ideal"):
                raise DataError(src, f"heliostats/{h.name}/actuator/actuator_{i}/type", f"unknown type {a.type!r}")

    def per_axis(key):
        return np.asarray([[a.parameters[key] for a in h.actuators] for h in hs])

    def dev(h, key):
        return h.deviations.get(key, 0.0)

    def vec(prefix):
        return np.asarray([[dev(h, f"{prefix}_{c}") for c in "enu"] for h in hs])

    actuators = LinearActuators(
        increment=jnp.asarray(per_axis("increment"), dtype),
        initial_stroke_length=jnp.asarray(per_axis("initial_stroke_length"), dtype),
        offset=jnp.asarray(per_axis("offset"), dtype),
        pivot_radius=jnp.asarray(per_axis("pivot_radius"), dtype),
        initial_angle=jnp.asarray(per_axis("initial_angle"), dtype),
        sign=jnp.asarray([[-1.0 if a.clockwise_axis_movement else 1.0 for a in h.actuators] for h in hs], dtype),
        min_counts=jnp.asarray([[a.min_max_motor_positions[0] for a in h.actuators] for h in hs], dtype),
        max_counts=jnp.asarray([[a.min_max_motor_positions[1] for a in h.actuators] for h in hs], dtype),
    )
    geometry = _build_geometry(
        jnp.asarray(np.stack([h.position for h in hs if h.position is not None]), dtype),
        actuators,
        jnp.asarray(vec("first_joint_translation"), dtype),
        jnp.asarray(vec("second_joint_translation"), dtype),
        jnp.asarray(vec("concentrator_translation"), dtype),
        jnp.asarray([[a.type == "ideal" for a in h.actuators] for h in hs]),
    )
    z = jnp.zeros(len(hs), dtype)
    model = ActuatorModel(
        alpha=jnp.asarray([-dev(h, "first_joint_tilt_n") for h in hs], dtype),
        beta=jnp.asarray([dev(h, "first_joint_tilt_u") for h in hs], dtype),
        gamma=jnp.asarray([-dev(h, "second_joint_tilt_n") for h in hs], dtype),
        delta=z,
        angle_offset=jnp.asarray([[dev(h, "second_joint_tilt_e"), 0.0] for h in hs], dtype),
        increment_scale=jnp.zeros((len(hs), 2), dtype),
        stroke_offset=jnp.zeros((len(hs), 2), dtype),
    )

    translations = np.asarray([[f.position for f in h.facets] for h in hs])
    canting = np.asarray([[f.canting for f in h.facets] for h in hs])
    cps = []
    for h, t, c in zip(hs, translations, canting, strict=True):
        cp = np.stack([f.control_points for f in h.facets])
        if np.all(cp[..., 2] == 0.0):  # flat facets: ARTIST cants them
            cps.append(np.einsum("fij,fuvj->fuvi", _canting_rotation(c), cp))
        else:  # already canted and translated
            cps.append(cp - t[:, None, None, :])
    cp = jnp.asarray(np.stack(cps), dtype)
    facets = NurbsFacets(
        control_points=cp,
        weights=jnp.ones(cp.shape[:-1], dtype),
        translations=jnp.asarray(translations, dtype),
        facet_mask=jnp.ones(cp.shape[:2], bool),
        degree=degrees[0],
    )
    layout = FacetLayout.from_arrays(
        *(jnp.asarray(x, dtype) for x in (translations, canting[..., 0, :], canting[..., 1, :]))
    )
    suns = [(k, s) for k, s in scenario.light_sources.items() if s.type == "sun" and s.distribution_type == "normal"]
    sunshape: AbstractSunShape = GaussianSun()
    if suns:
        name, sun = suns[0]
        if not 0.0 <= sun.covariance <= MAX_SPREAD_RAD**2:  # negative: a NaN sun; huge: a flux image of nothing
            raise DataError(
                src,
                f"lightsources/{name}/distribution_parameters/covariance",
                f"{sun.covariance!r}; expected the sun's variance per axis in [0, {MAX_SPREAD_RAD**2:g}] rad^2",
            )
        sunshape = GaussianSun(float(np.sqrt(sun.covariance)))
    return Scene(
        heliostat_ids=tuple(h.name for h in hs),
        origin_lla=np.asarray(scenario.plant_position_lla, np.float64),
        geometry=geometry,
        model=model,
        layout=layout,
        facets=facets,
        targets={k: _target(t, dtype) for k, t in scenario.planar_targets.items()},
        sunshape=sunshape,
        template=scenario,
    )


@eqx.filter_jit
def _exported_actuators(model: ActuatorModel, g: HeliostatGeometry) -> LinearActuators:
    """Actuator parameters that carry ``model``'s corrections: on linear axes the
    effective actuators (``angle_offset``, ``increment_scale``, ``stroke_offset``
    folded in, exact); on ideal axes an ``increment`` and ``initial_angle`` whose
    linearised law (what heliojax reads back) is the fitted linear map (fixed point
    on the slope, then the intercept; converges to machine precision in a few steps)."""
    act = model.effective_actuators(g)
    want_slope = g.linear_slope / (1.0 + model.increment_scale)
    want_intercept = g.linear_intercept + model.angle_offset
    trial = eqx.tree_at(
        lambda a: (a.increment, a.initial_angle), g.actuators, (g.actuators.increment, g.actuators.initial_angle)
    )
    for _ in range(8):
        slope, _ = trial.linearised()
        trial = eqx.tree_at(lambda a: a.increment, trial, trial.increment * slope / want_slope)
    _, intercept = trial.linearised()
    trial = eqx.tree_at(lambda a: a.initial_angle, trial, trial.initial_angle + want_intercept - intercept)
    ideal = g.ideal_axes
    return eqx.tree_at(
        lambda a: (a.increment, a.initial_angle, a.initial_stroke_length),
        act,
        (
            jnp.where(ideal, trial.increment, act.increment),
            jnp.where(ideal, trial.initial_angle, act.initial_angle),
            jnp.where(ideal, g.actuators.initial_stroke_length, act.initial_stroke_length),
        ),
    )


def scene_to_artist(scene: Scene, model: ActuatorModel | None = None, *, drop_delta: bool = False) -> ArtistScenario:
    """The scene, with the kinematics of ``model`` (batched like ``scene.geometry``;
    default ``scene.model``), as an :class:`heliojax.paint.ArtistScenario`.

    ``model``'s tilts become ARTIST's joint tilts, its actuator corrections the
    actuator parameters (see the module docstring).

    Raises:
        ValueError: ``model.delta`` is non-zero (no ARTIST counterpart) and
            ``drop_delta`` is False.
    """
    model = scene.model if model is None else model
    delta = np.asarray(model.delta, np.float64)
    if not drop_delta and np.any(delta != 0.0):
        raise ValueError(
            f"the mirror tilt delta (max |delta| = {np.max(np.abs(delta)):.3g} rad) has no ARTIST counterpart; "
            "pass drop_delta=True to write the model without it"
        )
    template = scene.template
    g = scene.geometry
    ideal = np.asarray(g.ideal_axes)
    act = _exported_actuators(model, g)
    np_ = lambda x: np.asarray(x, np.float64)  # noqa: E731
    inc, stroke, ang = np_(act.increment), np_(act.initial_stroke_length), np_(act.initial_angle)
    off, pivot, sign = np_(g.actuators.offset), np_(g.actuators.pivot_radius), np_(g.actuators.sign)
    lo, hi = np_(g.actuators.min_counts), np_(g.actuators.max_counts)
    alpha, beta, gamma = np_(model.alpha), np_(model.beta), np_(model.gamma)
    cp = np_(scene.facets.control_points)
    tr = np_(scene.facets.translations)
    ce, cn = np_(scene.layout.canting_e), np_(scene.layout.canting_n)
    j1, j2, cc = np_(g.joint_translation_1), np_(g.joint_translation_2), np_(g.concentrator_translation)
    by_name = {h.name: h for h in template.heliostats} if template is not None else {}
    heliostats = []
    for i, name in enumerate(scene.heliostat_ids):
        canting = np.stack([ce[i], cn[i]], axis=1)  # (f, 2, 3)
        rot = _canting_rotation(canting)
        flat = np.einsum("fji,fuvj->fuvi", rot, cp[i])  # de-canted
        if np.all(np.abs(flat[..., 2]) < 1e-9):
            points = flat * np.asarray([1.0, 1.0, 0.0])
        else:
            points = cp[i] + tr[i][:, None, None, :]
        facets = tuple(
            ArtistFacet(
                position=tr[i, k],
                canting=canting[k],
                control_points=points[k],
                degrees=(scene.facets.degree, scene.facets.degree),
            )
            for k in range(cp.shape[1])
        )
        actuators = tuple(
            ArtistActuator(
                type="ideal" if ideal[i, a] else "linear",
                clockwise_axis_movement=bool(sign[i, a] < 0),
                min_max_motor_positions=(int(lo[i, a]), int(hi[i, a])),
                parameters={
                    "increment": inc[i, a],
                    "initial_angle": ang[i, a],
                    "initial_stroke_length": stroke[i, a],
                    "offset": off[i, a],
                    "pivot_radius": pivot[i, a],
                },
            )
            for a in range(2)
        )
        deviations = {
            **{f"first_joint_translation_{c}": j1[i, k] for k, c in enumerate("enu")},
            "first_joint_tilt_n": -alpha[i],
            "first_joint_tilt_u": beta[i],
            **{f"second_joint_translation_{c}": j2[i, k] for k, c in enumerate("enu")},
            "second_joint_tilt_e": 0.0,
            "second_joint_tilt_n": -gamma[i],
            **{f"concentrator_translation_{c}": cc[i, k] for k, c in enumerate("enu")},
        }
        old = by_name.get(name)
        heliostats.append(
            ArtistHeliostat(
                name=name,
                id=old.id if old is not None else i + 1,
                position=np_(g.position[i]),
                kinematics_type="rigid_body",
                initial_orientation=np.asarray([0.0, -1.0, 0.0]),
                deviations=deviations,
                actuators=actuators,
                facets=facets,
            )
        )
    targets = {
        k: ArtistPlanarTarget(
            centre=np_(t.centre),
            normal=np_(t.normal),
            width=2.0 * float(t.half_width),
            height=2.0 * float(t.half_height),
        )
        for k, t in scene.targets.items()
    }
    lights = dict(template.light_sources) if template is not None else {}
    if isinstance(scene.sunshape, GaussianSun):
        old_sun = lights.get("sun_1")
        lights["sun_1"] = ArtistLightSource(
            type="sun",
            number_of_rays=old_sun.number_of_rays if old_sun is not None else 10,
            distribution_type="normal",
            mean=0.0,
            covariance=float(scene.sunshape.sigma) ** 2,
        )
    return ArtistScenario(
        source="<heliojax>",
        plant_position_lla=np.asarray(scene.origin_lla, np.float64),
        heliostats=tuple(heliostats),
        prototype=template.prototype if template is not None else None,
        planar_targets=targets,
        cylindrical_targets=dict(template.cylindrical_targets) if template is not None else {},
        light_sources=lights,
        number_of_heliostat_groups=template.number_of_heliostat_groups if template is not None else None,
        version=template.version if template is not None else 1.0,
    )


__all__ = ["Scene", "scene_from_artist", "scene_to_artist"]
