"""Kinematics: hand values, a second (quaternion) implementation of the chain,
round trips, jit/vmap/grad, float32 vs float64."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import heliojax as hj
from heliojax._beam import beam_error_components, beam_pointing_error, measured_normal, reflected_ray
from heliojax._geometry import sun_direction
from heliojax._heliostat import HeliostatGeometry, LinearActuators, RecordContext, chain_pose
from heliojax._kinematics import ActuatorModel, StoneModel, forward, inverse_aim, inverse_normal

# BE36's PAINT actuator values.
BE36 = LinearActuators(
    increment=jnp.array([154166.6667, 154166.6667]),
    initial_stroke_length=jnp.array([0.075676335, 0.078387399]),
    offset=jnp.array([0.335308, 0.340771]),
    pivot_radius=jnp.array([0.338095, 0.3191]),
    initial_angle=jnp.array([0.01366065, 0.937086489]),
    sign=jnp.array([1.0, -1.0]),
    min_counts=jnp.array([0.0, 0.0]),
    max_counts=jnp.array([69001.0, 75454.0]),
)
GEOM = HeliostatGeometry.build(
    jnp.array([0.9, 209.6, 1.7]), BE36, concentrator_translation=jnp.array([0.0, 0.175, 0.0])
)
AIM = jnp.array([0.0, -3.2, 122.9])


def _stone(**kw):
    base = dict(alpha=0.0, beta=0.0, gamma=0.0, delta=0.0, theta_k=0.0, tau_k=0.0, gr1=1.0, gr2=1.0)
    base.update(kw)
    return StoneModel(**{k: jnp.asarray(v, jnp.float64) for k, v in base.items()})


PERTURBED = _stone(alpha=2e-3, beta=-3e-3, gamma=1.5e-3, delta=-2e-3, theta_k=8e-3, tau_k=-6e-3, gr1=1.003, gr2=0.998)
PERTURBED_ACT = ActuatorModel(
    alpha=jnp.asarray(1e-3),
    beta=jnp.asarray(-2e-3),
    gamma=jnp.asarray(2e-3),
    delta=jnp.asarray(1e-3),
    angle_offset=jnp.array([5e-3, -0.03]),
    increment_scale=jnp.array([2e-3, -1e-3]),
    stroke_offset=jnp.array([1e-3, -5e-4]),
)


def test_actuator_law_hand_values():
    # Count 0 gives the initial angle; 34500 counts on axis 1 by hand (law of cosines).
    np.testing.assert_allclose(BE36.counts_to_angles(jnp.zeros(2)), [0.01366065, 0.937086489], atol=1e-15)
    s0, o, r = 0.075676335, 0.335308, 0.338095
    s = 34500 / 154166.6667 + s0
    psi = math.acos((o * o + r * r - s * s) / (2 * o * r))
    psi0 = math.acos((o * o + r * r - s0 * s0) / (2 * o * r))
    ang = BE36.counts_to_angles(jnp.array([34500.0, 0.0]))
    assert float(ang[0]) == pytest.approx(0.01366065 + (psi - psi0), abs=1e-14)
    # Axis 2 turns the other way (clockwise_axis_movement = 1).
    assert float(BE36.counts_to_angles(jnp.array([0.0, 30000.0]))[1]) < 0.937
    # Full strokes span the documented movement ranges (~0 .. pi/2 on axis 1).
    full = BE36.counts_to_angles(BE36.max_counts)
    assert 1.50 < float(full[0]) < 1.60
    assert -1.0 < float(full[1]) < -0.85
    # Inverse.
    c = jnp.array([12345.0, 54321.0])
    np.testing.assert_allclose(BE36.angles_to_counts(BE36.counts_to_angles(c)), c, atol=1e-8)


def test_linear_map_is_least_squares_line():
    slope, intercept = BE36.linearised(n=2001)
    c = np.linspace(0, 69001.0, 2001)
    ang = np.array([float(BE36.counts_to_angles(jnp.array([x, 0.0]))[0]) for x in c[::50]])
    fit = np.polyfit(c[::50], ang, 1)
    np.testing.assert_allclose(float(slope[0]), fit[0], rtol=2e-3)
    assert abs(float(intercept[0]) - fit[1]) < 5e-3


def test_chain_hand_values():
    geom = GEOM
    tilts = jnp.zeros(4)
    # theta = pi/2, tau = 0: the reference pose faces south; theta = 0 faces up.
    np.testing.assert_allclose(chain_pose(tilts, jnp.array([np.pi / 2, 0.0]), geom).normal, [0, -1, 0], atol=1e-15)
    np.testing.assert_allclose(chain_pose(tilts, jnp.array([0.0, 0.0]), geom).normal, [0, 0, 1], atol=1e-15)
    # tau > 0 turns the normal toward east.
    n = chain_pose(tilts, jnp.array([np.pi / 2, 0.1]), geom).normal
    np.testing.assert_allclose(n, [np.sin(0.1), -np.cos(0.1), 0], atol=1e-15)
    # The mirror centre sits V2M = (0, 0.175, 0) from axis 2: north of it at the
    # reference pose, below it when facing up.
    p = chain_pose(tilts, jnp.array([np.pi / 2, 0.0]), geom)
    np.testing.assert_allclose(p.centre, geom.position + jnp.array([0, 0.175, 0]), atol=1e-15)
    p0 = chain_pose(tilts, jnp.array([0.0, 0.0]), geom)
    np.testing.assert_allclose(p0.centre, geom.position + jnp.array([0, 0, -0.175]), atol=1e-15)
    # rotation maps the surface frame's +z to the normal and is orthonormal.
    np.testing.assert_allclose(p.rotation[:, 2], p.normal, atol=1e-15)
    np.testing.assert_allclose(p.rotation @ p.rotation.T, np.eye(3), atol=1e-14)


def _quat(axis, angle):
    axis = np.asarray(axis, float)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def _qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _qrot(q, v):
    qv = np.concatenate([[0.0], v])
    qc = q * np.array([1, -1, -1, -1])
    return _qmul(_qmul(q, qv), qc)[1:]


def _reference_normal(p, theta, tau):
    """Second implementation: unit quaternions (independent of the matrix code)."""
    ex, ey, ez = np.eye(3)
    q = _quat(ey, p["alpha"])
    for axis, ang in ((ez, p["beta"]), (ex, theta - np.pi / 2), (ey, p["gamma"]), (ez, tau), (ex, p["delta"])):
        q = _qmul(q, _quat(axis, ang))
    return _qrot(q, np.array([0.0, -1.0, 0.0]))


def test_chain_matches_quaternion_implementation():
    rng = np.random.default_rng(1)
    for _ in range(20):
        p = dict(zip(("alpha", "beta", "gamma", "delta"), rng.normal(0, 0.05, 4)))
        theta, tau = rng.uniform(0.2, 1.5), rng.uniform(-0.9, 0.9)
        pose = chain_pose(jnp.array([p["alpha"], p["beta"], p["gamma"], p["delta"]]), jnp.array([theta, tau]), GEOM)
        np.testing.assert_allclose(pose.normal, _reference_normal(p, theta, tau), atol=1e-14)


@pytest.mark.parametrize("model", [PERTURBED, PERTURBED_ACT], ids=["stone", "actuator"])
def test_inverse_round_trips(model):
    rng = np.random.default_rng(2)
    for _ in range(10):
        az, el = rng.uniform(-1.3, 1.3), rng.uniform(0.25, 1.1)
        sun = sun_direction(az, el)
        aim = AIM + jnp.asarray(rng.uniform(-2, 2, 3))
        counts = inverse_aim(model, GEOM, aim, sun)
        pose = forward(model, GEOM, counts)
        # The reflected central ray passes through the aim point.
        err = beam_pointing_error(pose, sun, aim)
        assert float(err) < 1e-9
        # counts -> normal -> counts.
        back = inverse_normal(model, GEOM, pose.normal)
        np.testing.assert_allclose(back, counts, atol=1e-6)
        np.testing.assert_allclose(forward(model, GEOM, back).normal, pose.normal, atol=1e-12)


def test_jit_equals_plain_and_vmap_equals_loop():
    rng = np.random.default_rng(3)
    counts = jnp.asarray(rng.uniform(5000, 60000, (16, 2)))
    plain = [forward(PERTURBED, GEOM, c) for c in counts]
    jitted = jax.jit(forward)
    vm = jax.vmap(lambda c: forward(PERTURBED, GEOM, c))(counts)
    for i, p in enumerate(plain):
        np.testing.assert_allclose(jitted(PERTURBED, GEOM, counts[i]).normal, p.normal, atol=1e-12)
        np.testing.assert_allclose(vm.normal[i], p.normal, atol=1e-12)
        np.testing.assert_allclose(vm.centre[i], p.centre, atol=1e-12)


def test_gradients_of_beam_error_match_finite_differences():
    sun = sun_direction(0.5, 0.7)
    counts = inverse_aim(_stone(), GEOM, AIM, sun)  # nominal aim; PERTURBED then misses by mrad
    view = hj.ParameterView.of(PERTURBED)
    vec = view.to_vector(PERTURBED)

    def err(v):
        return beam_pointing_error(forward(view.from_vector(PERTURBED, v), GEOM, counts), sun, AIM)

    assert float(err(vec)) > 5e-3
    g = jax.grad(err)(vec)
    for i in range(8):
        h = 1e-6
        e = jnp.zeros(8).at[i].set(h)
        fd = (err(vec + e) - err(vec - e)) / (2 * h)
        np.testing.assert_allclose(float(g[i]), float(fd), rtol=1e-5, atol=1e-9)


def test_float32_close_to_float64():
    counts = jnp.array([30000.0, 40000.0])
    p64 = forward(PERTURBED, GEOM, counts)
    m32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32), PERTURBED)
    g32 = jax.tree_util.tree_map(lambda x: x.astype(jnp.float32) if x.dtype == jnp.float64 else x, GEOM)
    p32 = forward(m32, g32, counts.astype(jnp.float32))
    assert p32.normal.dtype == jnp.float32
    np.testing.assert_allclose(p32.normal, p64.normal, atol=2e-6)
    np.testing.assert_allclose(p32.centre, p64.centre, atol=1e-4)


def test_measured_normal_and_error_components():
    sun = sun_direction(-0.4, 0.8)
    counts = inverse_aim(PERTURBED, GEOM, AIM, sun)
    pose = forward(PERTURBED, GEOM, counts)
    np.testing.assert_allclose(measured_normal(pose.centre, sun, AIM), pose.normal, atol=1e-12)
    # A spot displaced 0.2 m sideways on a plane ~213 m away is a ~0.94 mrad error.
    r = reflected_ray(pose, sun)
    dist = float(jnp.linalg.norm(AIM - pose.centre))
    side = jnp.cross(jnp.array([0.0, 0.0, 1.0]), r)
    side = side / jnp.linalg.norm(side)
    spot = pose.centre + dist * r + 0.2 * side
    comp = beam_error_components(pose, sun, spot)
    assert float(beam_pointing_error(pose, sun, spot)) == pytest.approx(0.2 / dist, rel=1e-4)
    assert float(comp[0]) == pytest.approx(0.2 / dist, rel=1e-4) and abs(float(comp[1])) < 1e-9


def test_context_is_optional_and_batched():
    ctx = RecordContext.from_sun(jnp.stack([sun_direction(0.1, 0.5)] * 3), unix_time=1.7e9)
    assert ctx.sun.shape == (3, 3) and ctx.approach.shape == (3, 2)
    assert np.all(np.asarray(ctx.unix_time) == 1.7e9)
