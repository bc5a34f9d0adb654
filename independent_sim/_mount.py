"""Kinematics of a Jülich linear-actuator heliostat, own formulation with unit quaternions (w, x, y, z).

Internal conventions (converted to PAINT only at the file boundary):
- frame: local ENU metres (x east, y north, z up), quaternions rotate body vectors into ENU;
- axis 1 ("tilt"): rotation about the body east axis; internally the mirror's *elevation* e1 = pi/2 - theta1,
  where theta1 is PAINT's actuator-1 angle (tilt of the normal from the zenith toward south);
- axis 2 ("turn"): rotation about the tilted body up axis by theta2 (PAINT's actuator-2 angle, positive
  turns a south-facing normal toward east);
- the rest normal is the properties file's `initial_orientation` (south), the mirror centre is the
  concentrator translation carried by the full chain.
- linear actuator: stroke = counts / increment + initial_stroke_length; the triangle angle opposite the
  stroke is acos((offset^2 + pivot^2 - stroke^2) / (2 offset pivot)); the joint angle is initial_angle plus
  (clockwise_axis_movement = 0) or minus (= 1) the change of that angle from the initial stroke.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


def quat_axis_angle(axis, angle) -> np.ndarray:
    """Unit quaternion(s) (..., 4) for a rotation by `angle` (rad, broadcast) about unit `axis` (3,)."""
    angle = np.asarray(angle, dtype=float)
    axis = np.asarray(axis, dtype=float)
    half = 0.5 * angle
    return np.concatenate([np.cos(half)[..., None], np.sin(half)[..., None] * axis], axis=-1)


def _cross(a, b) -> np.ndarray:
    a, b = np.broadcast_arrays(a, b)
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def quat_mul(p, q) -> np.ndarray:
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - np.sum(pv * qv, axis=-1, keepdims=True)
    v = pw * qv + qw * pv + _cross(pv, qv)
    return np.concatenate([w, v], axis=-1)


def quat_rotate(q, v) -> np.ndarray:
    """Rotate vector(s) v (..., 3) by unit quaternion(s) q (..., 4)."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def small_rotation(rotvec) -> np.ndarray:
    """Quaternion of a rotation vector (rad, (3,))."""
    rotvec = np.asarray(rotvec, dtype=float)
    angle = float(np.linalg.norm(rotvec))
    if angle == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return quat_axis_angle(rotvec / angle, angle)


EAST, NORTH, UP = np.eye(3)


@dataclass(frozen=True)
class Actuator:
    """One linear actuator (PAINT properties fields); lengths in metres, increment in counts per metre."""

    increment: float
    initial_stroke: float
    offset: float
    pivot: float
    initial_angle: float
    clockwise: bool

    def triangle_angle(self, stroke):
        c = (self.offset**2 + self.pivot**2 - np.asarray(stroke) ** 2) / (2.0 * self.offset * self.pivot)
        return np.arccos(np.clip(c, -1.0, 1.0))

    def stroke(self, counts):
        return np.asarray(counts, dtype=float) / self.increment + self.initial_stroke

    def angle_from_stroke(self, stroke):
        change = self.triangle_angle(stroke) - self.triangle_angle(self.initial_stroke)
        return self.initial_angle - change if self.clockwise else self.initial_angle + change

    def stroke_from_angle(self, angle):
        change = (self.initial_angle - angle) if self.clockwise else (angle - self.initial_angle)
        tri = change + self.triangle_angle(self.initial_stroke)
        return np.sqrt(self.offset**2 + self.pivot**2 - 2.0 * self.offset * self.pivot * np.cos(tri))

    def angle(self, counts):
        return self.angle_from_stroke(self.stroke(counts))

    def counts(self, angle):
        return (self.stroke_from_angle(angle) - self.initial_stroke) * self.increment


@dataclass(frozen=True)
class Mount:
    """A heliostat: position (ENU m), actuators, rest normal, translations, and the plant's small errors.

    base_q: rotation of the pedestal; between_q: rotation between the two axes; mirror_q: mirror on axis 2;
    zero_1/zero_2: joint zero offsets (rad, added to the actuator angle).
    """

    position: np.ndarray
    act1: Actuator
    act2: Actuator
    rest_normal: np.ndarray
    joint2_translation: np.ndarray
    mirror_translation: np.ndarray
    base_q: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    between_q: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    mirror_q: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    zero_1: float = 0.0
    zero_2: float = 0.0

    def with_changes(self, **kw) -> Mount:
        return replace(self, **kw)

    def chain(self, theta1, theta2):
        """Quaternions (outer, full) for joint angles theta1, theta2 (rad, broadcast)."""
        elevation = 0.5 * np.pi - (np.asarray(theta1, dtype=float) + self.zero_1)
        q1 = quat_axis_angle(EAST, -elevation)
        q2 = quat_axis_angle(UP, np.asarray(theta2, dtype=float) + self.zero_2)
        outer = quat_mul(np.broadcast_to(self.base_q, q1.shape), q1)
        inner = quat_mul(
            quat_mul(np.broadcast_to(self.between_q, q2.shape), q2), np.broadcast_to(self.mirror_q, q2.shape)
        )
        return outer, quat_mul(outer, inner)

    def pose(self, theta1, theta2):
        """Mirror normal (..., 3) and mirror centre (..., 3, ENU m) for joint angles (rad)."""
        outer, full = self.chain(theta1, theta2)
        normal = quat_rotate(full, np.broadcast_to(self.rest_normal, full.shape[:-1] + (3,)))
        arm = self.joint2_translation + quat_rotate(
            quat_mul(
                np.broadcast_to(self.between_q, full.shape),
                quat_axis_angle(UP, np.asarray(theta2, dtype=float) + self.zero_2),
            ),
            np.broadcast_to(self.mirror_translation, full.shape[:-1] + (3,)),
        )
        centre = self.position + quat_rotate(outer, arm)
        return normal, centre

    def joint_angles_for_normal(self, normal, iterations: int = 20):
        """Joint angles (theta1, theta2) that point the mirror normal along `normal` (..., 3); Newton."""
        normal = np.asarray(normal, dtype=float)
        t1 = 0.5 * np.pi - np.arcsin(np.clip(normal[..., 2], -1, 1))
        t2 = np.arctan2(normal[..., 0], -normal[..., 1])
        h = 1e-7
        for _ in range(iterations):
            n0, _c = self.pose(t1, t2)
            na, _c = self.pose(t1 + h, t2)
            nb, _c = self.pose(t1, t2 + h)
            r = n0 - normal
            ja, jb = (na - n0) / h, (nb - n0) / h
            a11, a12, a22 = np.sum(ja * ja, -1), np.sum(ja * jb, -1), np.sum(jb * jb, -1)
            b1, b2 = np.sum(ja * r, -1), np.sum(jb * r, -1)
            det = a11 * a22 - a12 * a12
            s1, s2 = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
            t1, t2 = t1 - s1, t2 - s2
            if max(np.max(np.abs(s1)), np.max(np.abs(s2))) < 1e-13:
                break
        return t1, t2


def reflect(incoming_to_sun, normal):
    """Reflected beam direction for a unit vector toward the sun and a unit mirror normal."""
    return 2.0 * np.sum(incoming_to_sun * normal, -1, keepdims=True) * normal - incoming_to_sun


def hit_plane(origin, direction, plane_point, plane_normal):
    """Intersection of rays with a plane (ENU m)."""
    t = np.sum((plane_point - origin) * plane_normal, -1, keepdims=True) / np.sum(
        direction * plane_normal, -1, keepdims=True
    )
    return origin + t * direction


def aim_normal(mount: Mount, sun, aim_point, iterations: int = 12):
    """Joint angles so that the beam from the mirror centre hits `aim_point` (fixed point on the centre)."""
    _n, centre = mount.pose(np.full(sun.shape[:-1], 0.8), np.zeros(sun.shape[:-1]))
    t1 = t2 = None
    for _ in range(iterations):
        to_aim = aim_point - centre
        to_aim = to_aim / np.linalg.norm(to_aim, axis=-1, keepdims=True)
        bis = sun + to_aim
        bis = bis / np.linalg.norm(bis, axis=-1, keepdims=True)
        t1, t2 = mount.joint_angles_for_normal(bis)
        _n, new_centre = mount.pose(t1, t2)
        moved = float(np.max(np.abs(new_centre - centre)))
        centre = new_centre
        if moved < 1e-10:
            break
    return t1, t2
