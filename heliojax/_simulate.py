"""Simulator: synthetic heliostats and calibration records from the same ``forward``.

A simulated record is produced the way a plant produces one:

1. the plant's *controller model* (nominal parameters unless given) computes the
   motor counts that should put the sun's reflection on the aim point
   (:func:`heliojax.inverse_aim`), rounded to whole counts;
2. the heliostat's *true model* (true parameters, optionally wrapped by effects)
   turns those counts into the real mirror pose (:func:`heliojax.forward`);
3. the **injection point** ``perturb_pose(pose, context) -> pose`` may then
   perturb the true pose by an unmodelled effect (for the discovery workflow);
   effects that are kinematic models (wrapping a base model) may be used as the
   true model instead;
4. the central ray, reflected at the true pose and deviated by Gaussian
   measurement noise (``noise_mrad`` per tangent-plane component, or
   ``noise_m`` on the target plane), is intersected with the target plane: that
   is the measured focal spot.

:func:`write_simulation` writes the records as a PAINT-layout directory that
:func:`heliojax.load_paint_directory` reads back unchanged.
"""

from __future__ import annotations

import datetime as dt
import math
import typing
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ._beam import reflected_ray, tangent_basis
from ._fleet import Fleet, LoadReport
from ._geometry import TargetPlane, direction_to_azimuth_elevation, enu_to_wgs84, intersect_plane, normalize
from ._heliostat import HeliostatGeometry, LinearActuators, Pose, RecordContext
from ._kinematics import AbstractKinematicModel, StoneModel, forward, inverse_aim
from ._limits import MAX_SYNTHETIC_HELIOSTATS, MAX_SYNTHETIC_RECORDS, count_problem, real_problem
from ._sun import solar_position
from .paint import CalibrationRecord, HeliostatProperties, TargetEntry, TowerFile, write_paint_directory

JUELICH_LAT_LON_ALT = (50.913421122592574, 6.387824755874856, 87.0)
"""The PAINT plant reference point of the Jülich solar tower (WGS84 deg, deg, m)."""

# Typical Jülich actuator values (PAINT properties of the shared records: the median
# over the fleet of each field), used to make synthetic heliostats.
_TYPICAL_ACTUATORS = dict(
    increment=(154166.6667, 154166.6667),
    initial_stroke_length=(0.0757, 0.0768),
    offset=(0.335308, 0.340771),
    pivot_radius=(0.338095, 0.3191),
    initial_angle=(0.0137, 0.9381),
    sign=(1.0, -1.0),
    min_counts=(0.0, 0.0),
    max_counts=(69000.0, 75000.0),
)


def _check_sizes(function: str, records: tuple[str, ...] = (), **counts: typing.Any) -> None:
    """Refuse a count of heliostats or records that is no whole number, below 1 or past
    :data:`~heliojax._limits.MAX_SYNTHETIC_HELIOSTATS` (before anything is allocated:
    XLA had failed after minutes with an out-of-memory error); ``records`` names the
    counts whose product is a number of records (at most
    :data:`~heliojax._limits.MAX_SYNTHETIC_RECORDS`)."""
    for name, value in counts.items():
        limit = MAX_SYNTHETIC_RECORDS if name in records else MAX_SYNTHETIC_HELIOSTATS
        problem = count_problem(value, limit)
        if problem is not None:
            raise ValueError(f"{function}: {name} {problem}")
    if records:
        total = math.prod(int(counts[name]) for name in records)
        if total > MAX_SYNTHETIC_RECORDS:
            raise ValueError(
                f"{function}: {' x '.join(records)} = {total:,} records, more than the "
                f"{MAX_SYNTHETIC_RECORDS:,} a synthetic fleet may have"
            )


def check_magnitudes(function: str, **values: typing.Any) -> None:
    """Refuse a magnitude (a noise level, a spread of random errors) that is no finite
    number >= 0 (:func:`heliojax._limits.real_problem`), naming ``function`` and the
    argument: a NaN had made every record or model NaN, a negative one flipped the
    draws, without a word. Traced values are not checked."""
    for name, value in values.items():
        if isinstance(value, jax.core.Tracer):  # pyright: ignore[reportAttributeAccessIssue]
            continue
        problem = real_problem(value, minimum=0.0)
        if problem is not None:
            raise ValueError(f"{function}: {name} {problem}")


def typical_actuators(n: int | None = None, dtype=jnp.float64) -> LinearActuators:
    """Jülich-like :class:`LinearActuators` (batched to ``(n, 2)`` if ``n`` is given)."""
    if n is not None:
        _check_sizes("typical_actuators", n=n)
    fields = {k: jnp.asarray(v, dtype) for k, v in _TYPICAL_ACTUATORS.items()}
    if n is not None:
        fields = {k: jnp.broadcast_to(v, (n, 2)) for k, v in fields.items()}
    return LinearActuators(**fields)


@eqx.filter_jit
def synthetic_geometry(key: PRNGKeyArray, n: int, dtype=jnp.float64) -> HeliostatGeometry:
    """``n`` heliostats in a field 60-300 m north of the tower (ENU m), Jülich-like
    actuators with small manufacturing scatter, mirror 0.175 m off axis 2."""
    _check_sizes("synthetic_geometry", n=n)
    k1, k2, k3 = jax.random.split(key, 3)
    east = jax.random.uniform(k1, (n,), dtype, -130.0, 130.0)
    north = jax.random.uniform(k2, (n,), dtype, 60.0, 300.0)
    position = jnp.stack([east, north, jnp.full((n,), 1.5, dtype)], -1)
    act = typical_actuators(n, dtype)
    scatter = jax.random.normal(k3, (n, 2), dtype)
    act = eqx.tree_at(lambda a: a.initial_stroke_length, act, act.initial_stroke_length + 1e-3 * scatter)
    return HeliostatGeometry.build(
        position, act, concentrator_translation=jnp.broadcast_to(jnp.asarray([0.0, 0.175, 0.0], dtype), (n, 3))
    )


@eqx.filter_jit
def random_stone_models(
    key: PRNGKeyArray, n: int, angle_sigma: float = 3e-3, gear_sigma: float = 2e-3, dtype=jnp.float64
) -> StoneModel:
    """``n`` true Stone models with angles ~ N(0, angle_sigma) rad (offsets 3x
    larger) and gear ratios ~ 1 + N(0, gear_sigma), batched.

    Raises:
        ValueError: ``n`` no whole number >= 1, or a sigma not a finite number >= 0 (a
            NaN had made every true model NaN).
    """
    _check_sizes("random_stone_models", n=n)
    check_magnitudes("random_stone_models", angle_sigma=angle_sigma, gear_sigma=gear_sigma)
    z = jax.vmap(lambda k: jax.random.normal(k, (n,), dtype))(jax.random.split(key, 8))  # (8, n)
    ang = [angle_sigma * z[i] for i in range(4)]
    off = [3 * angle_sigma * z[i] for i in range(4, 6)]
    gr = [1.0 + gear_sigma * z[i] for i in range(6, 8)]
    return StoneModel(*ang, *off, *gr)


@eqx.filter_jit
def calibration_target(dtype=jnp.float64) -> TargetPlane:
    """A 6 x 7 m vertical calibration target facing north, centred 123 m up on the
    tower's north face (like PAINT's ``solar_tower_juelich_lower``, in ENU m)."""
    return TargetPlane.from_corners(
        jnp.asarray([3.0, -3.2, 126.5], dtype),
        jnp.asarray([-3.0, -3.2, 126.5], dtype),
        jnp.asarray([3.0, -3.2, 119.3], dtype),
        jnp.asarray([-3.0, -3.2, 119.3], dtype),
    )


@eqx.filter_jit
def calibration_times(
    key: PRNGKeyArray,
    shape: tuple[int, ...],
    start_unix: float = 1.6540e9,
    days: float = 365.0,
    latitude_deg: float = JUELICH_LAT_LON_ALT[0],
    longitude_deg: float = JUELICH_LAT_LON_ALT[1],
    min_elevation_deg: float = 15.0,
) -> tuple[Float[Array, "..."], Float[Array, "... 3"]]:
    """Random calibration times (unix s) and sun vectors, daytime only.

    Days are uniform over ``days`` from ``start_unix``; the hour (UTC) is uniform
    over 04-20 h and resampled (a fixed number of rounds, vectorised) until the sun
    is above ``min_elevation_deg``. Where no round finds it that high (short winter
    days, high latitudes), the candidate with the highest sun is kept, and local
    solar noon is always among the candidates, so no record is ever drawn at night
    wherever the sun rises that day.

    **Returns:** ``(times, sun)``: times ``shape`` (unix s, whole seconds) and unit
    vectors towards the sun ``(*shape, 3)`` (local ENU).
    """
    axes = {f"shape[{i}]": n for i, n in enumerate(shape)}
    _check_sizes("calibration_times", tuple(axes), **axes)

    k_day, k_hour = jax.random.split(key)
    midnight = np.floor(start_unix / 86400.0) * 86400.0  # hours below are UTC hours of the day
    day = jnp.floor(jax.random.uniform(k_day, shape, jnp.float64, 0.0, days))
    rounds = 12  # random candidate hours per record; the first with the sun high enough wins
    hour = jax.vmap(lambda kk: jax.random.uniform(kk, shape, jnp.float64, 4.0, 20.0))(jax.random.split(k_hour, rounds))
    noon = jnp.full((1, *shape), (12.0 - longitude_deg / 15.0) % 24.0)  # local solar noon (UTC h), within ~16 min
    hour = jnp.concatenate([hour, noon], axis=0)
    cand = jnp.round(midnight + day[None] * 86400.0 + hour * 3600.0)  # (rounds + 1, *shape), whole seconds

    def sun_at(times: Float[Array, "..."]) -> tuple[Float[Array, "..."], Float[Array, "... 3"]]:
        pos = solar_position(times, latitude_deg, longitude_deg, JUELICH_LAT_LON_ALT[2])
        return pos.elevation, pos.direction_enu()

    # one round at a time: the solar position's intermediates (its periodic terms) for
    # all rounds at once took 8.6 GB at 5,000 x 50 records
    elevation, direction = jax.lax.map(sun_at, cand)
    good = elevation[:rounds] > jnp.deg2rad(min_elevation_deg)
    first = jnp.where(jnp.any(good, axis=0), jnp.argmax(good, axis=0), jnp.argmax(elevation, axis=0))
    t = jnp.take_along_axis(cand, first[None], axis=0)[0]
    sun = jnp.take_along_axis(direction, first[None, ..., None], axis=0)[0]
    return t, sun


@eqx.filter_jit
def _simulate_core(perturb_pose, true_models, controller_models, geometry, context, ang_noise, pos_noise, target, aim):
    def one_record(true_model, ctrl_model, g, ctx, an, pn):
        counts = jnp.round(inverse_aim(ctrl_model, g, aim, ctx.sun))
        counts = jnp.clip(counts, g.actuators.min_counts, g.actuators.max_counts)
        pose = forward(true_model, g, counts, ctx)
        if perturb_pose is not None:
            pose = perturb_pose(pose, ctx)
        sun = true_model.sun(g, ctx)
        r = reflected_ray(pose, sun)
        true_hit = intersect_plane(pose.centre, r, target)
        e1, e2 = tangent_basis(r)
        r_noisy = normalize(r + an[0] * e1 + an[1] * e2)
        hit = intersect_plane(pose.centre, r_noisy, target)
        spot = hit.point + pn[0] * target.u_axis + pn[1] * target.v_axis
        return counts, spot, true_hit.point, hit.hit

    def one_heliostat(tm, cm, g, ctx, an, pn):
        return jax.vmap(lambda c, a, p: one_record(tm, cm, g, c, a, p))(ctx, an, pn)

    return jax.vmap(one_heliostat)(true_models, controller_models, geometry, context, ang_noise, pos_noise)


def simulate_records(
    key: PRNGKeyArray,
    true_models: AbstractKinematicModel,
    geometry: HeliostatGeometry,
    context: RecordContext,
    target: TargetPlane,
    aim_point: Float[Array, "3"] | None = None,
    *,
    controller_models: AbstractKinematicModel | None = None,
    noise_mrad: float = 0.0,
    noise_m: float = 0.0,
    perturb_pose: Callable[[Pose, RecordContext], Pose] | None = None,
) -> Fleet:
    """Simulate calibration records for a batch of heliostats (vmapped), as a
    :class:`heliojax.Fleet` (the one record container): ``mask`` marks the records
    whose noisy spot hit the target; ids ``S000, S001, ...``; one target.

    Args:
        key: PRNG key of the measurement noise.
        true_models: batched (leading axis ``H``) true kinematic models.
        geometry: batched geometry ``(H, ...)``.
        context: batched ``(H, M)`` record contexts (sun direction, time, weather).
        target: the calibration target (one plane for all records).
        aim_point: ``(3,)`` ENU m; default the target centre.
        controller_models: batched models the plant uses to aim; default nominal Stone.
        noise_mrad: std of the angular noise per tangent-plane component, mrad.
        noise_m: std of additional spot noise on the target plane per axis, m.
        perturb_pose: the injection point for an unmodelled effect, applied to the
            true pose of every record.

    Raises:
        ValueError: ``noise_mrad`` or ``noise_m`` not finite and >= 0 (a NaN had made
            every spot NaN and every record masked, without a word).
    """
    check_magnitudes("simulate_records", noise_mrad=noise_mrad, noise_m=noise_m)
    h = geometry.position.shape[0]
    m = context.sun.shape[1]
    dtype = geometry.position.dtype
    aim = target.centre if aim_point is None else jnp.asarray(aim_point, dtype)
    if controller_models is None:
        controller_models = jax.vmap(lambda _: StoneModel.nominal(dtype))(jnp.arange(h))
    k_ang, k_pos = jax.random.split(key)
    ang_noise = noise_mrad * 1e-3 * jax.random.normal(k_ang, (h, m, 2), dtype)
    pos_noise = noise_m * jax.random.normal(k_pos, (h, m, 2), dtype)
    counts, spot, true_spot, hit = _simulate_core(
        perturb_pose, true_models, controller_models, geometry, context, ang_noise, pos_noise, target, aim
    )
    del true_spot
    return Fleet(
        geometry=geometry,
        counts=counts,
        context=eqx.tree_at(lambda c: c.target, context, jnp.zeros((h, m), jnp.int32)),
        focal_spot=spot,
        record_id=jnp.asarray(np.arange(h * m).reshape(h, m) + 100000, jnp.int64),
        mask=hit,
        targets=jax.tree.map(lambda x: jnp.asarray(x)[None], target),
        origin_lla=jnp.asarray(JUELICH_LAT_LON_ALT, dtype),
        ids=tuple(f"S{i:03d}" for i in range(h)),
        target_names=("calibration_target",),
        report=LoadReport(source="<simulation>", records_loaded=h * m, heliostats_loaded=h),
    )


@eqx.filter_jit
def synthetic_contexts(
    key: PRNGKeyArray, n_heliostats: int, n_records: int, *, weather: bool = True, **time_kwargs
) -> RecordContext:
    """Random calibration contexts ``(H, M)``: times and suns from
    :func:`calibration_times`, plus (if ``weather``) a simple synthetic weather
    (temperature with seasonal and daily cycles, Weibull-like wind speed, uniform
    wind direction); records are in chronological order per heliostat and
    ``approach`` is left 0 (the simulator fills it from the counts' order) and
    ``target`` is 0 (the one simulated target)."""
    _check_sizes("synthetic_contexts", ("n_heliostats", "n_records"), n_heliostats=n_heliostats, n_records=n_records)
    k_t, k_w1, k_w2, k_w3 = jax.random.split(key, 4)
    t, sun = calibration_times(k_t, (n_heliostats, n_records), **time_kwargs)
    order = jnp.argsort(t, axis=1)
    t = jnp.take_along_axis(t, order, 1)
    sun = jnp.take_along_axis(sun, order[..., None], 1)
    shape = t.shape
    if weather:
        doy = (t / 86400.0) % 365.25
        hour = (t / 3600.0) % 24.0
        temperature = (
            10.0
            - 8.0 * jnp.cos(2 * jnp.pi * (doy - 15.0) / 365.25)
            + 4.0 * jnp.sin(2 * jnp.pi * (hour - 9.0) / 24.0)
            + 2.0 * jax.random.normal(k_w1, shape)
        )
        wind_speed = 4.0 * jnp.sqrt(-jnp.log(jax.random.uniform(k_w2, shape, minval=1e-6, maxval=1.0)))
        wind_direction = jax.random.uniform(k_w3, shape, minval=0.0, maxval=2 * jnp.pi)
    else:
        temperature = wind_speed = wind_direction = jnp.full(shape, jnp.nan)
    return RecordContext(
        sun=sun,
        unix_time=t,
        temperature=temperature,
        wind_speed=wind_speed,
        wind_direction=wind_direction,
        approach=jnp.zeros(shape + (2,)),
        target=jnp.zeros(shape, jnp.int32),
    )


@eqx.filter_jit
def approach_directions(counts: Float[Array, "H M 2"], mask: Bool[Array, "H M"] | None = None) -> Float[Array, "H M 2"]:
    """Sign of the last motion of each axis before each record, from the
    chronological order of a heliostat's records (+1 counts increased, -1
    decreased, 0 for the first record or no motion). Masked records are skipped
    (the previous valid record is used)."""
    counts = jnp.asarray(counts)
    if mask is None:
        mask = jnp.ones(counts.shape[:2], bool)

    def per_heliostat(c, m):
        def step(prev, x):
            ci, mi = x
            d = jnp.where(mi & jnp.all(jnp.isfinite(prev)), jnp.sign(ci - prev), 0.0)
            new_prev = jnp.where(mi, ci, prev)
            return new_prev, d

        _, d = jax.lax.scan(step, jnp.full((2,), jnp.nan, c.dtype), (c, m))
        return d

    return jax.vmap(per_heliostat)(counts, mask)


def to_numpy_tree(tree):
    """Device arrays -> numpy (for writing files)."""
    return jax.tree_util.tree_map(np.asarray, tree)


# --------------------------------------------------------------------------------------
# Simulated fleet -> PAINT files
# --------------------------------------------------------------------------------------


def _vec3(values: typing.Any) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return (x, y, z)


def synthetic_tower(target: TargetPlane, origin_lla=JUELICH_LAT_LON_ALT, name: str = "solar_tower_juelich_lower"):
    """A :class:`heliojax.TowerFile` holding ``target`` (corners converted to WGS84)."""
    origin = jnp.asarray(origin_lla, jnp.float64)
    uv = {
        "upper_left": (-1.0, 1.0),
        "upper_right": (1.0, 1.0),
        "lower_left": (-1.0, -1.0),
        "lower_right": (1.0, -1.0),
        "center": (0.0, 0.0),
    }
    points = {}
    for key, (a, b) in uv.items():
        enu = target.from_plane(jnp.asarray([a * target.half_width, b * target.half_height]))
        points[key] = _vec3(np.asarray(enu_to_wgs84(enu, origin)))
    entry = TargetEntry(name=name, type="planar", normal=_vec3(np.asarray(target.normal)), points=points)
    return TowerFile(plant_id="SIMULATED", origin_lla=_vec3(origin_lla), targets={name: entry})


def synthetic_properties(geometry: HeliostatGeometry, ids, origin_lla=JUELICH_LAT_LON_ALT):
    """PAINT :class:`heliojax.HeliostatProperties` of a batched synthetic geometry."""
    g = to_numpy_tree(geometry)
    lla = np.asarray(enu_to_wgs84(jnp.asarray(g.position, jnp.float64), jnp.asarray(origin_lla, jnp.float64)))
    a = g.actuators
    out = []
    for i, hid in enumerate(ids):
        acts = []
        for k in range(2):
            lo = float(a.min_counts[i, k])
            hi = float(a.max_counts[i, k])
            acts.append(
                {
                    "type_axis": "linear",
                    "min_increment": int(lo),
                    "max_increment": int(hi),
                    "increment": float(a.increment[i, k]),
                    "offset_shift": 0,
                    "initial_stroke_length": float(a.initial_stroke_length[i, k]),
                    "offset": float(a.offset[i, k]),
                    "pivot_radius": float(a.pivot_radius[i, k]),
                    "radius_shift": 0,
                    "clockwise_axis_movement": 0 if a.sign[i, k] > 0 else 1,
                    "initial_angle": float(a.initial_angle[i, k]),
                    "movement_speed": 0,
                }
            )
        out.append(
            HeliostatProperties(
                heliostat_id=hid,
                position_lla=_vec3(lla[i]),
                width=3.22,
                height=2.56,
                initial_orientation=(0.0, -1.0, 0.0),
                actuators=(acts[0], acts[1]),
                joint_translation_1=_vec3(g.joint_translation_1[i]),
                joint_translation_2=_vec3(g.joint_translation_2[i]),
                concentrator_translation=_vec3(g.concentrator_translation[i]),
            )
        )
    return out


def simulation_to_records(
    sim: Fleet,
    ids,
    mask=None,
    origin_lla=JUELICH_LAT_LON_ALT,
    target_name: str = "solar_tower_juelich_lower",
    first_record_id: int = 100000,
):
    """Raw :class:`heliojax.CalibrationRecord` s of simulated records (degrees and
    WGS84 at this boundary; times as ISO strings; weather in file units)."""
    counts = np.asarray(sim.counts)
    h, m = counts.shape[:2]
    mask = np.ones((h, m), bool) if mask is None else np.asarray(mask)
    spot_lla = np.asarray(enu_to_wgs84(jnp.asarray(sim.focal_spot, jnp.float64), jnp.asarray(origin_lla, jnp.float64)))
    az, el = direction_to_azimuth_elevation(jnp.asarray(sim.context.sun, jnp.float64))
    az, el = np.rad2deg(np.asarray(az)), np.rad2deg(np.asarray(el))
    t = np.asarray(sim.context.unix_time)
    temp = np.asarray(sim.context.temperature)
    wind = np.asarray(sim.context.wind_speed)
    wdir = np.rad2deg(np.asarray(sim.context.wind_direction))
    records = []
    rid = first_record_id
    for i in range(h):
        for j in range(m):
            if not mask[i, j]:
                continue
            when = None
            if np.isfinite(t[i, j]):
                when = dt.datetime.fromtimestamp(float(t[i, j]), dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
            weather = {
                "temperature": float(temp[i, j]),
                "wind_speed": float(wind[i, j]),
                "wind_direction": float(wdir[i, j]),
                "dni": float("nan"),
                "humidity": float("nan"),
                "pressure": float("nan"),
            }
            spot = _vec3(spot_lla[i, j])
            records.append(
                CalibrationRecord(
                    record_id=rid,
                    heliostat_id=ids[i],
                    axis_1_counts=int(counts[i, j, 0]),
                    axis_2_counts=int(counts[i, j, 1]),
                    target_name=target_name,
                    sun_azimuth_deg=float(az[i, j]),
                    sun_elevation_deg=float(el[i, j]),
                    focal_spot_helios=spot,
                    focal_spot_utis=spot,
                    datetime=when,
                    weather=weather,
                )
            )
            rid += 1
    return records


def write_simulation(
    out_dir,
    sim: Fleet,
    geometry: HeliostatGeometry,
    target: TargetPlane,
    ids=None,
    mask=None,
    origin_lla=JUELICH_LAT_LON_ALT,
):
    """Write simulated records as a PAINT-layout directory (tower file, properties,
    calibration records, ``calibration-timestamps.json``, ``calibration-with-weather.csv``)
    that :func:`heliojax.load_paint_directory` reads back.

    Only records with ``mask`` (default: those whose spot hit the target) are
    written. Returns ``(path, tower, properties, records)`` so callers can build
    the same fleet in memory with :func:`heliojax.records_to_fleet`.
    """
    h = geometry.position.shape[0]
    ids = [f"SIM{i:04d}" for i in range(h)] if ids is None else list(ids)
    mask = np.asarray(sim.mask) if mask is None else np.asarray(mask)
    tower = synthetic_tower(target, origin_lla)
    props = synthetic_properties(geometry, ids, origin_lla)
    records = simulation_to_records(sim, ids, mask, origin_lla, target_name=next(iter(tower.targets)))
    path = write_paint_directory(out_dir, tower, props, records, weather=True)
    return path, tower, props, records


__all__ = [
    "JUELICH_LAT_LON_ALT",
    "approach_directions",
    "calibration_target",
    "calibration_times",
    "random_stone_models",
    "simulate_records",
    "synthetic_contexts",
    "synthetic_geometry",
    "simulation_to_records",
    "synthetic_properties",
    "synthetic_tower",
    "typical_actuators",
    "write_simulation",
]
