"""Effect library: each effect against a hand calculation or a second
implementation, zero effects reproduce the base, wrappers compose in any order,
the effect-wrapped model fits through the one fit core."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax._heliostat import chain_pose
from heliojax.effects import (
    EFFECT_NAMES,
    TARGET_SLOTS,
    ActuatorGeometry,
    Backlash,
    Clock,
    EffectModel,
    EncoderWobble,
    GravitySag,
    OffsetDrift,
    OffsetStep,
    Refraction,
    SurveyHeliostat,
    SurveyTarget,
    Thermal,
    Wind,
    add_effects,
    effect_class,
    make_effect,
    standard_refraction,
    with_data_references,
    with_effects,
)

ACT = hj.LinearActuators(
    increment=jnp.array([154166.6667, 154166.6667]),
    initial_stroke_length=jnp.array([0.075676335, 0.078387399]),
    offset=jnp.array([0.335308, 0.340771]),
    pivot_radius=jnp.array([0.338095, 0.3191]),
    initial_angle=jnp.array([0.01366065, 0.937086489]),
    sign=jnp.array([1.0, -1.0]),
    min_counts=jnp.array([0.0, 0.0]),
    max_counts=jnp.array([69001.0, 75454.0]),
)
GEOM = hj.HeliostatGeometry.build(
    jnp.array([0.9, 209.6, 1.7]), ACT, concentrator_translation=jnp.array([0.0, 0.175, 0.0])
)
COUNTS = jnp.array([30000.0, 40000.0])
SUN = hj.sun_direction(jnp.deg2rad(20.0), jnp.deg2rad(40.0))
FOCAL = jnp.array([0.3, -3.2, 122.5])
STONE = hj.StoneModel(*[jnp.asarray(v) for v in (1e-3, -2e-3, 5e-4, -1e-3, 4e-3, -3e-3, 1.002, 0.998)])
ACTUATOR = hj.ActuatorModel.nominal(jnp.float64)


def _context(**kw):
    base = dict(
        sun=SUN,
        unix_time=jnp.asarray(1.66e9),
        temperature=jnp.asarray(25.0),
        wind_speed=jnp.asarray(6.0),
        wind_direction=jnp.asarray(1.0),
        approach=jnp.array([1.0, -1.0]),
        target=jnp.asarray(0, jnp.int32),
    )
    base.update({k: jnp.asarray(v) for k, v in kw.items()})
    return hj.RecordContext(**base)


def test_effect_names_are_the_documented_list():
    assert EFFECT_NAMES == (
        "actuator_geometry",
        "backlash",
        "thermal",
        "wind",
        "clock",
        "gravity_sag",
        "encoder_wobble",
        "refraction",
        "survey_heliostat",
        "survey_target",
        "offset_drift",
    )
    for name in EFFECT_NAMES:
        cls = effect_class(name)
        assert cls.NAME == name
        assert cls.__doc__ and "Physical meaning" in cls.__doc__ and "signature" in cls.__doc__
        view = hj.ParameterView.of(cls.nominal(STONE, jnp.float64))
        assert view.n_parameters >= 1
        assert all(s > 0 for s in view.scales) and all(t is not None and t > 0 for t in view.typical)
    with pytest.raises(ValueError, match="unknown effect"):
        effect_class("magnetism")


@pytest.mark.parametrize("base_kind", ["stone8", "actuator"])
def test_zero_effects_reproduce_the_base(base_kind):
    base = STONE if base_kind == "stone8" else hj.ActuatorModel.nominal(jnp.float64)
    effects = tuple(make_effect(n, base) for n in EFFECT_NAMES)
    model = EffectModel(base, effects)
    ctx = _context()
    np.testing.assert_allclose(
        model.beam_components(GEOM, COUNTS, ctx, FOCAL), base.beam_components(GEOM, COUNTS, ctx, FOCAL), atol=1e-15
    )
    np.testing.assert_allclose(model.pose(GEOM, COUNTS, ctx).normal, base.pose(GEOM, COUNTS).normal, atol=1e-15)
    np.testing.assert_allclose(model.sun(GEOM, ctx), SUN, atol=1e-15)
    # The inverse is the base's (controllers aim with the base model).
    np.testing.assert_allclose(model.counts(GEOM, jnp.array([0.5, 0.1])), base.counts(GEOM, jnp.array([0.5, 0.1])))


def _angle_shift(effect, ctx, base=STONE):
    """Joint-angle correction of ``effect`` recovered from the pose: the chain at the
    base angles plus a shift reproduces the effect model's normal."""
    model = EffectModel(base, (effect,))
    return model.record_angles(GEOM, COUNTS, ctx) - base.joint_angles(GEOM, COUNTS)


def test_backlash_is_half_the_dead_band_behind_the_motion():
    w = jnp.array([3e-4, 5e-4])
    ctx = _context(approach=jnp.array([1.0, -1.0]))
    joint = Backlash(width=w, stroke_width=jnp.zeros(2))
    d = _angle_shift(joint, ctx)
    slope_sign = np.sign(np.asarray(GEOM.linear_slope))
    # axis 1 approached from below (+1): behind = -w/2 in the direction the angle grows.
    np.testing.assert_allclose(d, [-1.5e-4 * slope_sign[0] * 1, -2.5e-4 * slope_sign[1] * -1], rtol=1e-12)
    # unknown approach: no correction
    np.testing.assert_allclose(_angle_shift(joint, _context(approach=jnp.zeros(2))), 0.0, atol=0)


def test_thermal_hand_value_and_nan_temperature():
    eff = Thermal(coefficient=jnp.array([1.5e-5, -1e-5]), expansion=jnp.zeros(2), reference=jnp.asarray(10.0))
    np.testing.assert_allclose(_angle_shift(eff, _context(temperature=25.0)), [2.25e-4, -1.5e-4], rtol=1e-12)
    # the spindle's expansion: a gear-ratio change in proportion to the temperature
    ang = np.asarray(STONE.joint_angles(GEOM, COUNTS))
    eff2 = Thermal(coefficient=jnp.zeros(2), expansion=jnp.array([1.2e-5, 2e-5]), reference=jnp.asarray(10.0))
    want = [1.8e-4 * ang[0], 3e-4 * ang[1]]
    np.testing.assert_allclose(_angle_shift(eff2, _context(temperature=25.0)), want, rtol=1e-9)
    np.testing.assert_allclose(_angle_shift(eff, _context(temperature=jnp.nan)), 0.0, atol=0)

    # no NaN reaches the gradient when the temperature is unknown
    def loss(k):
        m = EffectModel(STONE, (Thermal(coefficient=k, expansion=jnp.zeros(2), reference=jnp.asarray(10.0)),))
        return jnp.sum(m.beam_components(GEOM, COUNTS, _context(temperature=jnp.nan), FOCAL) ** 2)

    g = jax.grad(loss)(jnp.array([1e-5, 1e-5]))
    assert np.all(np.isfinite(g)) and np.all(g == 0)


def test_thermal_spindle_expansion_under_the_actuator_law():
    """With a base that follows the law of cosines, the spindle's expansion lengthens the
    whole stroke: against the triangle computed by hand (NumPy), and the gear-ratio
    form for an axis the plant declares ideal."""
    dt, s = 15.0, np.array([1.2e-5, 5e-5])
    eff = make_effect("thermal", ACTUATOR, thermal_scale_1=s[0], thermal_scale_2=s[1], thermal_reference_c=10.0)
    assert eff.law == "actuator"
    act = jax.tree.map(np.asarray, GEOM.actuators)

    def angle(stroke):  # the triangle's angle at the pivot, law of cosines
        return np.arccos((act.offset**2 + act.pivot_radius**2 - stroke**2) / (2 * act.offset * act.pivot_radius))

    stroke = np.asarray(COUNTS) / act.increment + act.initial_stroke_length
    want = act.sign * (angle(stroke * (1 + s * dt)) - angle(stroke))
    got = _angle_shift(eff, _context(temperature=25.0), base=ACTUATOR)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    # not the gear-ratio form: through the triangle the shift is not proportional to the angle
    gear = s * dt * np.asarray(ACTUATOR.joint_angles(GEOM, COUNTS))
    assert np.all(np.abs(got - gear) > 0.05 * np.abs(want))
    ideal = eqx.tree_at(lambda g: g.ideal_axes, GEOM, jnp.array([False, True]))
    shifted = EffectModel(ACTUATOR, (eff,)).record_angles(ideal, COUNTS, _context(temperature=25.0))
    got_ideal = shifted - ACTUATOR.joint_angles(ideal, COUNTS)
    np.testing.assert_allclose(got_ideal[0], want[0], rtol=1e-9)
    np.testing.assert_allclose(got_ideal[1], s[1] * dt * ACTUATOR.joint_angles(ideal, COUNTS)[1], rtol=1e-9)


def test_backlash_of_the_spindle_under_the_actuator_law():
    """With a base that follows the law of cosines, backlash is a dead band of the
    stroke: against the triangle by hand (NumPy); the joint's width is fixed there and
    the stroke's is fitted (the other way round for a linear base)."""
    b = np.array([2e-4, 1e-4])  # m of stroke
    eff = make_effect("backlash", ACTUATOR, backlash_stroke_1=b[0], backlash_stroke_2=b[1])
    assert eff.law == "actuator" and eff.fixed_parameter_fields() == ("width",)
    assert make_effect("backlash").fixed_parameter_fields() == ("stroke_width",)
    act = jax.tree.map(np.asarray, GEOM.actuators)

    def angle(stroke):
        return np.arccos((act.offset**2 + act.pivot_radius**2 - stroke**2) / (2 * act.offset * act.pivot_radius))

    stroke = np.asarray(COUNTS) / act.increment + act.initial_stroke_length
    approach = np.array([1.0, -1.0])
    want = act.sign * (angle(stroke - 0.5 * approach * b) - angle(stroke))
    got = _angle_shift(eff, _context(approach=jnp.asarray(approach)), base=ACTUATOR)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    # a lag: behind the motion in the joint angle too
    slope = np.asarray(GEOM.linear_slope)
    assert np.all(np.sign(got) == -np.sign(slope) * approach)
    np.testing.assert_allclose(_angle_shift(eff, _context(approach=jnp.zeros(2)), base=ACTUATOR), 0.0, atol=0)


def test_offset_drift_hand_value_and_nan_time():
    """Half a Julian year after the reference: half the yearly rate on each joint;
    an unknown time gets no correction, and no NaN in the gradient."""
    t_ref = 1.66e9
    eff = OffsetDrift(rate=jnp.array([1e-3, -2e-3]), reference=jnp.asarray(t_ref))
    half_year = 0.5 * 365.25 * 86400.0
    np.testing.assert_allclose(_angle_shift(eff, _context(unix_time=t_ref + half_year)), [5e-4, -1e-3], rtol=1e-12)
    np.testing.assert_allclose(_angle_shift(eff, _context(unix_time=t_ref)), 0.0, atol=1e-18)
    np.testing.assert_allclose(_angle_shift(eff, _context(unix_time=jnp.nan)), 0.0, atol=0)

    def loss(r):
        m = EffectModel(STONE, (OffsetDrift(rate=r, reference=jnp.asarray(t_ref)),))
        return jnp.sum(m.beam_components(GEOM, COUNTS, _context(unix_time=jnp.nan), FOCAL) ** 2)

    g = jax.grad(loss)(jnp.array([1e-3, 1e-3]))
    assert np.all(np.isfinite(g)) and np.all(g == 0)


def test_offset_step_is_the_base_with_the_earlier_zeros_before_its_date():
    """Before the change time the model is the base with both joint zeros ``jump`` lower
    (the base's own offsets being the current state), from it on the base itself; a
    record without a time is the current state, as is a pose without any context.
    The time is not fitted by default, and the jump's gradient is finite."""
    base = eqx.tree_at(lambda m: m.angle_offset, ACTUATOR, jnp.array([2e-3, -1e-3]))
    jump = jnp.array([1.5e-3, -0.7e-3])
    t_c = 1.66e9
    model = EffectModel(base, (OffsetStep(jump=jump, time=jnp.asarray(t_c)),))
    earlier = eqx.tree_at(lambda m: m.angle_offset, base, base.angle_offset - jump)
    for t, reference in ((t_c - 86400.0, earlier), (t_c, base), (t_c + 1e6, base), (jnp.nan, base)):
        ctx = _context(unix_time=t)
        np.testing.assert_allclose(
            model.beam_components(GEOM, COUNTS, ctx, FOCAL),
            reference.beam_components(GEOM, COUNTS, ctx, FOCAL),
            atol=1e-15,
        )
    np.testing.assert_allclose(model.joint_angles(GEOM, COUNTS), base.joint_angles(GEOM, COUNTS), atol=0)
    free = hj.ParameterView.of(model)
    names = [n for n, f in zip(free.names, free.free, strict=True) if f]
    assert "change_point_jump_1" in names and "change_point_time" not in names

    def loss(j):
        m = EffectModel(base, (OffsetStep(jump=j, time=jnp.asarray(t_c)),))
        return jnp.sum(m.beam_components(GEOM, COUNTS, _context(unix_time=t_c - 1.0), FOCAL) ** 2)

    g = jax.jit(jax.grad(loss))(jump)
    assert np.all(np.isfinite(g)) and np.any(g != 0)
    assert "change_point" not in EFFECT_NAMES  # added by discovery where a step is found, never screened


def test_wind_head_on_and_cross():
    eff = Wind(coefficient=jnp.array([5e-6, 7e-6]), droop=jnp.asarray(0.0))
    normal = STONE.pose(GEOM, COUNTS).normal
    facing = float(np.arctan2(normal[0], normal[1]))
    d_head = _angle_shift(eff, _context(wind_speed=10.0, wind_direction=facing))
    np.testing.assert_allclose(d_head, [5e-4, 0.0], atol=1e-15)
    d_cross = _angle_shift(eff, _context(wind_speed=10.0, wind_direction=facing + math.pi / 2))
    np.testing.assert_allclose(d_cross, [0.0, 7e-4], atol=1e-15)
    np.testing.assert_allclose(_angle_shift(eff, _context(wind_speed=jnp.nan)), 0.0, atol=0)


def test_wind_droop_tips_the_normal_toward_the_horizon_by_c0_v_squared_from_any_direction():
    # the direction-independent part of the wind load: at v = 10 m/s and c_0 = 1e-6
    # rad/(m/s)^2 the normal's elevation drops by 1e-4 rad, its azimuth stays, whatever
    # the direction the wind comes from; no speed (NaN) switches it off
    c0, v = 1e-6, 10.0
    eff = Wind(coefficient=jnp.zeros(2), droop=jnp.asarray(c0))
    for base in (STONE, ACTUATOR):
        n0 = np.asarray(base.pose(GEOM, COUNTS).normal)
        model = EffectModel(base, (eff,))
        for direction in (0.0, 1.0, 4.0):
            n1 = np.asarray(model.pose(GEOM, COUNTS, _context(wind_speed=v, wind_direction=direction)).normal)
            e0, e1 = np.arcsin(n0[2]), np.arcsin(n1[2])
            np.testing.assert_allclose(e1 - e0, -c0 * v * v, rtol=1e-3)
            np.testing.assert_allclose(np.arctan2(n1[0], n1[1]), np.arctan2(n0[0], n0[1]), atol=1e-3 * c0 * v * v)
        np.testing.assert_allclose(_angle_shift(eff, _context(wind_speed=jnp.nan), base=base), 0.0, atol=0)


def test_gravity_sag_tips_the_normal_toward_the_horizon_by_g_cos_elevation():
    # gravity acts vertically: to first order the normal's elevation drops by g cos(e) and
    # its azimuth stays, for the Stone chain and for the actuator model alike
    g = 1e-4
    for base in (STONE, ACTUATOR):
        n0 = np.asarray(base.pose(GEOM, COUNTS).normal)
        model = EffectModel(base, (GravitySag(sag=jnp.asarray(g)),))
        n1 = np.asarray(model.pose(GEOM, COUNTS, _context()).normal)
        e0, e1 = np.arcsin(n0[2]), np.arcsin(n1[2])
        np.testing.assert_allclose(e1 - e0, -g * np.cos(e0), rtol=1e-3)
        np.testing.assert_allclose(np.arctan2(n1[0], n1[1]), np.arctan2(n0[0], n0[1]), atol=1e-3 * g)
        # the pose is the chain at corrected angles (no kink between angles and normal)
        d = _angle_shift(GravitySag(sag=jnp.asarray(g)), _context(), base=base)
        want = chain_pose(base.tilts(), base.joint_angles(GEOM, COUNTS) + d, GEOM).normal
        np.testing.assert_allclose(n1, want, atol=1e-15)


def test_encoder_wobble_hand_value():
    eff = EncoderWobble(a=jnp.array([3e-4, 0.0]), b=jnp.array([0.0, 2e-4]))
    ang = np.asarray(STONE.joint_angles(GEOM, COUNTS))
    d = _angle_shift(eff, _context())
    np.testing.assert_allclose(d, [3e-4 * np.cos(2 * ang[0]), 2e-4 * np.sin(2 * ang[1])], rtol=1e-12)


def test_actuator_curvature_one_turns_stone_into_the_actuator_law():
    # Nominal Stone (gr = 1, offsets 0) follows the least-squares line of the law;
    # adding the full curvature reproduces the nominal actuator model exactly.
    stone = hj.StoneModel.nominal(jnp.float64)
    eff = ActuatorGeometry(curvature=jnp.ones(2), pivot_scale=jnp.zeros(2))
    model = EffectModel(stone, (eff,))
    act = hj.ActuatorModel.nominal(jnp.float64)
    for c in (jnp.array([1000.0, 2000.0]), COUNTS, jnp.array([68000.0, 74000.0])):
        np.testing.assert_allclose(model.joint_angles(GEOM, c), act.joint_angles(GEOM, c), atol=1e-13)
    # and the curvature is large: tens of mrad over the range
    lin = stone.joint_angles(GEOM, jnp.array([68000.0, 74000.0]))
    assert np.max(np.abs(np.asarray(act.joint_angles(GEOM, jnp.array([68000.0, 74000.0])) - lin))) > 5e-3


def test_pivot_scale_equals_a_scaled_pivot_radius():
    act = hj.ActuatorModel.nominal(jnp.float64)  # nominal: the correction uses the nominal actuators
    s = jnp.array([0.015, -0.01])
    model = EffectModel(act, (ActuatorGeometry(curvature=jnp.zeros(2), pivot_scale=s),))
    scaled = eqx.tree_at(lambda g: g.actuators.pivot_radius, GEOM, GEOM.actuators.pivot_radius * (1 + s))
    np.testing.assert_allclose(model.joint_angles(GEOM, COUNTS), act.joint_angles(scaled, COUNTS), atol=1e-14)


def test_clock_matches_the_solar_position_code():
    lat, lon, alt = 50.913421122592574, 6.387824755874856, 87.0
    times = jnp.array([1.66e9 + 3600 * h for h in (11.0, 13.0, 15.0, 17.0)])  # 2022-08-09, 09-15 UTC
    s0 = hj.solar_position(times, lat, lon, alt).direction_enu()
    for dt in (30.0, -90.0):
        s1 = hj.solar_position(times + dt, lat, lon, alt).direction_enu()
        clock = Clock(
            offset=jnp.asarray(dt), drift=jnp.asarray(0.0), reference=jnp.asarray(1.6e9), latitude_deg=jnp.asarray(lat)
        )
        s2 = jax.vmap(clock.adjust_sun)(s0, hj.RecordContext.from_sun(s0, times))
        moved = np.linalg.norm(np.asarray(s1 - s0), axis=1)
        err = np.linalg.norm(np.asarray(s2 - s1), axis=1)
        assert np.all(moved > 2e-3)
        assert np.all(err < 5e-3 * moved)
    # drift: dt grows linearly from the reference; unknown time -> no correction
    c = Clock(
        offset=jnp.asarray(1.0), drift=jnp.asarray(0.1), reference=jnp.asarray(1.6e9), latitude_deg=jnp.asarray(lat)
    )
    np.testing.assert_allclose(c.clock_error(jnp.array([1.6e9 + 10 * 86400, jnp.nan])), [2.0, 0.0])


def test_standard_refraction_against_tables():
    # Almanac refraction (10 deg C, 1010 hPa): ~5.3' at 10 deg, ~0.98' at 45 deg, 0 at the zenith.
    r = np.degrees(np.asarray(standard_refraction(jnp.deg2rad(jnp.array([10.0, 45.0, 90.0]))))) * 60
    np.testing.assert_allclose(r[:2], [5.3, 0.98], rtol=0.05)
    assert abs(r[2]) < 1e-3
    eff = Refraction(scale=jnp.asarray(1.0))
    s = eff.adjust_sun(SUN, _context())
    el0 = np.arcsin(float(SUN[2]))
    el1 = np.arcsin(float(s[2]))
    np.testing.assert_allclose(el1 - el0, float(standard_refraction(jnp.asarray(el0))), rtol=1e-9)
    np.testing.assert_allclose(np.arctan2(s[0], -s[1]), np.arctan2(SUN[0], -SUN[1]), atol=1e-14)  # same azimuth


def test_survey_effects_move_heliostat_and_spot():
    d = jnp.array([0.05, -0.1, 0.02])
    ctx = _context()
    moved = eqx.tree_at(lambda g: g.position, GEOM, GEOM.position + d)
    m = EffectModel(STONE, (SurveyHeliostat(delta=d),))
    np.testing.assert_allclose(
        m.beam_components(GEOM, COUNTS, ctx, FOCAL), STONE.beam_components(moved, COUNTS, ctx, FOCAL), atol=1e-15
    )
    m = EffectModel(STONE, (SurveyTarget(delta=jnp.zeros((TARGET_SLOTS, 3)).at[0].set(d)),))
    np.testing.assert_allclose(
        m.beam_components(GEOM, COUNTS, ctx, FOCAL), STONE.beam_components(GEOM, COUNTS, ctx, FOCAL + d), atol=1e-15
    )


# records on targets 0, 1, 2, 3, unknown (-1) and beyond the slots (4)
TARGETS = jnp.array([0, 1, 2, 3, -1, TARGET_SLOTS], jnp.int32)
SHIFTS = jnp.array([[0.05, -0.1, 0.02], [-0.08, 0.0, 0.11], [0.0, 0.03, -0.04], [0.02, 0.02, 0.02]])


def _per_target_beams(model, targets=TARGETS):
    n = targets.shape[0]
    ctx = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x)), _context())
    ctx = eqx.tree_at(lambda c: c.target, ctx, targets)
    return jax.vmap(lambda x: model.beam_components(GEOM, COUNTS, x, FOCAL))(ctx)


@pytest.mark.parametrize("k", range(TARGET_SLOTS))
def test_survey_target_moves_exactly_the_spots_on_its_target(k):
    """A shift d on target k moves the spot of exactly the records measured on k by d;
    the others, those of an unknown target (-1) and of a target beyond the slots
    are unchanged."""
    d = SHIFTS[k]
    model = EffectModel(STONE, (SurveyTarget(delta=jnp.zeros((TARGET_SLOTS, 3)).at[k].set(d)),))
    got = _per_target_beams(model)
    plain = STONE.beam_components(GEOM, COUNTS, _context(), FOCAL)
    moved = STONE.beam_components(GEOM, COUNTS, _context(), FOCAL + d)
    for i, t in enumerate(np.asarray(TARGETS)):
        np.testing.assert_allclose(got[i], moved if t == k else plain, rtol=0, atol=1e-15)
    assert float(jnp.max(jnp.abs(moved - plain))) > 1e-5  # a visible shift (d_perp / ~250 m)


def test_survey_target_all_targets_jit_and_gradient():
    """Every target shifted at once: each record sees its own target's shift (the
    same under jit); the gradient of a record's beam error in the offsets equals
    finite differences and is zero for the other targets' offsets (and for a record
    of an unknown target: no NaN, no gradient)."""
    model = EffectModel(STONE, (SurveyTarget(delta=SHIFTS),))
    got = _per_target_beams(model)
    for i, t in enumerate(np.asarray(TARGETS)):
        spot = FOCAL + (SHIFTS[t] if 0 <= t < TARGET_SLOTS else 0.0)
        np.testing.assert_allclose(got[i], STONE.beam_components(GEOM, COUNTS, _context(), spot), atol=1e-15)
    # jit may fuse differently: equal to rounding (a few ulps of a unit vector)
    np.testing.assert_allclose(np.asarray(jax.jit(_per_target_beams)(model)), np.asarray(got), rtol=0, atol=1e-15)

    def beam(delta, target):
        ctx = eqx.tree_at(lambda c: c.target, _context(), jnp.asarray(target, jnp.int32))
        return EffectModel(STONE, (SurveyTarget(delta=delta),)).beam_components(GEOM, COUNTS, ctx, FOCAL)[0]

    for target in (1, -1):
        g = np.asarray(jax.grad(beam)(SHIFTS, target))
        assert np.all(np.isfinite(g))
        fd = np.zeros_like(g)
        eps = 1e-6
        for t in range(TARGET_SLOTS):
            for c in range(3):
                up, down = SHIFTS.at[t, c].add(eps), SHIFTS.at[t, c].add(-eps)
                fd[t, c] = (float(beam(up, target)) - float(beam(down, target))) / (2 * eps)
        np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
        others = [t for t in range(TARGET_SLOTS) if t != target]
        np.testing.assert_array_equal(g[others], 0.0)
        assert (np.abs(g[target]).max() > 1e-4) == (target >= 0)


def test_survey_target_parameters_are_named_per_target_slot():
    view = hj.ParameterView.of(SurveyTarget.nominal(STONE, jnp.float64))
    assert view.names == tuple(f"survey_target_{k}_{c}" for k in range(1, TARGET_SLOTS + 1) for c in "enu")
    e = make_effect("survey_target", survey_target_2_u=0.07)
    expected = np.zeros((TARGET_SLOTS, 3))
    expected[1, 2] = 0.07
    np.testing.assert_array_equal(np.asarray(e.delta), expected)
    # the slots a fleet's valid records use (the others are fixed by discovery)
    from heliojax.discovery import simulate_fleet

    fleet, _ = simulate_fleet(1, 2, 6)
    fleet = eqx.tree_at(lambda f: f.context.target, fleet, jnp.array([[0, 2, 2, -1, 0, 5]] * 2, jnp.int32))
    used = e.driven(fleet).reshape(TARGET_SLOTS, 3)
    np.testing.assert_array_equal(used[:, 0], [True, False, True, False])
    assert fleet.target_index is fleet.context.target  # one array, not a copy


def test_add_effects_appends_and_wrappers_nest():
    m = add_effects(STONE, [make_effect("backlash")])
    m2 = add_effects(m, [make_effect("thermal")])
    assert [e.NAME for e in m2.effects] == ["backlash", "thermal"]
    with pytest.raises(ValueError, match="repeated"):
        add_effects(m2, [make_effect("thermal")])
    # an EffectModel inside an EffectModel keeps both layers' behaviour
    nested = EffectModel(m, (make_effect("thermal", thermal_1=2e-5, thermal_2=0.0, thermal_reference_c=10.0),))
    flat = add_effects(
        STONE,
        [make_effect("backlash"), make_effect("thermal", thermal_1=2e-5, thermal_2=0.0, thermal_reference_c=10.0)],
    )
    ctx = _context()
    np.testing.assert_allclose(
        nested.beam_components(GEOM, COUNTS, ctx, FOCAL), flat.beam_components(GEOM, COUNTS, ctx, FOCAL), atol=1e-15
    )
    assert nested.label() == "stone8+backlash+thermal"


def test_with_effects_model_view():
    model = with_effects(hj.StoneModel.nominal(jnp.float64), ["thermal", "clock", "actuator_geometry"])
    assert model.label() == "stone8+thermal+clock+actuator_geometry"
    view = hj.ParameterView.of(model)
    assert view.names[:8] == ("alpha", "beta", "gamma", "delta", "theta_k", "tau_k", "gr1", "gr2")
    assert {"thermal_1", "thermal_2", "clock_offset", "clock_drift", "curvature_1"} <= set(view.free_names)
    assert "pivot_scale_1" in view.names and "pivot_scale_1" not in view.free_names
    assert "thermal_reference_c" not in view.names  # references are not parameters
    hash(view)  # a static jit argument
    act = hj.ParameterView.of(with_effects(hj.ActuatorModel.nominal(jnp.float64), ["actuator_geometry"]))
    assert "pivot_scale_1" in act.free_names and "curvature_1" not in act.free_names
    assert "stroke_offset_1" in act.names and "stroke_offset_1" not in act.free_names
    with pytest.raises(ValueError):
        with_effects(hj.StoneModel.nominal(jnp.float64), ["wind", "wind"])
    # nominal effects predict what the base predicts
    np.testing.assert_allclose(
        model.beam_components(GEOM, COUNTS, _context(), FOCAL),
        hj.StoneModel.nominal(jnp.float64).beam_components(GEOM, COUNTS, _context(), FOCAL),
        atol=1e-15,
    )
    # a value put in by name comes back out (vector round trip through the pytree)
    p = np.array(view.to_vector(model))
    p[view.names.index("thermal_2")] = 2e-5
    back = view.from_vector(model, jnp.asarray(p))
    assert float(back.effects[0].coefficient[1]) == 2e-5
    np.testing.assert_array_equal(np.asarray(view.to_vector(back)), p)
    refs = hj.set_references(model, {"thermal_reference_c": 12.0})
    assert float(refs.effects[0].reference) == 12.0


def test_free_set_is_a_pytree_partition():
    model = hj.ActuatorModel.nominal(jnp.float64)
    free = hj.default_free(model)
    assert jax.tree.structure(free) == jax.tree.structure(model)
    assert not free.stroke_offset and free.alpha
    freed = eqx.tree_at(lambda f: f.stroke_offset, free, True)
    assert "stroke_offset_2" in hj.ParameterView.of(model, freed).free_names
    fixed, _ = eqx.partition(model, free)
    assert fixed.stroke_offset is None and fixed.alpha is not None


def test_wrappers_compose_in_any_order():
    """Neural correction and effects keep each other's behaviour whichever wraps which."""
    from heliojax.neural import NeuralCorrection, init_residual_networks

    net = jax.tree.map(lambda x: x[0] if eqx.is_array(x) else x, init_residual_networks(jax.random.key(0), 1))
    # give the network a non-zero output layer so that its correction is visible
    net = jax.tree.map(lambda x: x + 0.1 if eqx.is_inexact_array(x) else x, net)
    scale = jnp.asarray(1e-3)
    thermal = make_effect("thermal", thermal_1=3e-5, thermal_2=-2e-5, thermal_reference_c=10.0)
    ctx = _context()
    nn_outside = NeuralCorrection(add_effects(STONE, [thermal]), net, scale)
    nn_inside = add_effects(NeuralCorrection(STONE, net, scale), [thermal])
    plain = STONE.record_angles(GEOM, COUNTS, ctx)
    d_nn = NeuralCorrection(STONE, net, scale).correction(GEOM, COUNTS)
    d_th = jnp.array([3e-5, -2e-5]) * (25.0 - 10.0)
    assert float(jnp.max(jnp.abs(d_nn))) > 1e-5
    for model in (nn_outside, nn_inside):
        np.testing.assert_allclose(model.record_angles(GEOM, COUNTS, ctx), plain + d_nn + d_th, atol=1e-14)
        assert model.pose(GEOM, COUNTS, ctx).normal.shape == (3,)
    np.testing.assert_allclose(
        nn_outside.beam_components(GEOM, COUNTS, ctx, FOCAL),
        nn_inside.beam_components(GEOM, COUNTS, ctx, FOCAL),
        atol=1e-14,
    )


@pytest.mark.slow
def test_psd_inverse_leaves_out_parameters_that_nothing_determines():
    """An all-zero row and column (a parameter no row depends on) is left out: the
    rest is the inverse of the remaining block (numpy), the dead row and column are 0."""
    rng = np.random.default_rng(0)
    j = rng.normal(size=(12, 4))
    block = j.T @ j
    full = np.zeros((6, 6))
    keep = [0, 2, 3, 5]
    full[np.ix_(keep, keep)] = block
    got = np.asarray(hj.fitting.psd_inverse(jnp.asarray(full)))
    expected = np.zeros((6, 6))
    expected[np.ix_(keep, keep)] = np.linalg.inv(block)
    np.testing.assert_allclose(got, expected, rtol=1e-10, atol=1e-14)
    # a singular determined block is still reported as singular (NaN), not hidden
    singular = full.copy()
    singular[np.ix_(keep, keep)] = np.outer(j[0], j[0])
    assert np.isnan(np.asarray(hj.fitting.psd_inverse(jnp.asarray(singular)))).any()


def test_fit_covariance_of_a_per_heliostat_survey_target_model_is_finite():
    """A survey-target slot that no record of a heliostat uses has a zero Jacobian
    column: the fit reports its standard deviation as NaN and keeps the covariance
    of every determined parameter finite (it used to be NaN throughout)."""
    from heliojax.discovery import simulate_fleet

    fleet, _ = simulate_fleet(3, 3, 30, noise_mrad=0.1)
    targets = jnp.asarray(np.tile(np.arange(30) % 2 * 2, (3, 1)), jnp.int32)  # targets 0 and 2
    fleet = eqx.tree_at(lambda f: f.context.target, fleet, targets)
    res = hj.fit(with_effects(hj.StoneModel.nominal(jnp.float64), ["survey_target"]), fleet, max_steps=64)
    names = res.view.names
    unused = [i for i, n in enumerate(names) if n.startswith(("survey_target_2_", "survey_target_4_"))]
    used = [i for i in range(len(names)) if i not in unused]
    std = np.asarray(res.std)
    assert np.isnan(std[:, unused]).all()
    assert np.isfinite(std[:, used]).all() and (std[:, used] > 0).all()
    cov = np.asarray(res.covariance)
    free = list(res.view.free_index)
    rows = [free.index(i) for i in used]
    assert np.isfinite(cov).all()
    np.testing.assert_allclose(
        np.sqrt(np.diagonal(cov[:, rows][:, :, rows], axis1=1, axis2=2)), std[:, used], rtol=1e-12
    )


def test_fit_recovers_an_effect_through_the_wrapped_model():
    """A model with effects is again a model: the fit core fits it unchanged."""
    from heliojax.discovery import simulate_fleet

    true = make_effect("thermal", thermal_1=3e-5, thermal_2=-2e-5, thermal_reference_c=8.0)
    fleet, _ = simulate_fleet(3, 4, 40, effects=[true], noise_mrad=0.1)
    model0 = with_data_references(with_effects(hj.StoneModel.nominal(jnp.float64), ["thermal"]), fleet)
    res = hj.fit(model0, fleet, max_steps=64)
    params = np.asarray(res.parameters())
    k1 = params[:, res.view.names.index("thermal_1")]
    k2 = params[:, res.view.names.index("thermal_2")]
    np.testing.assert_allclose(np.median(k1), 3e-5, rtol=0.2)
    np.testing.assert_allclose(np.median(k2), -2e-5, rtol=0.25)
    assert float(np.max(np.asarray(res.rms_mrad))) < 0.2
