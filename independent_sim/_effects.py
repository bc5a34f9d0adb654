"""Hidden effects, injected at the physical level (actuator stroke, joint, mirror, clock, sun, camera).

Each effect has one amplitude in a physical unit (`EFFECTS[name].unit`); `draw_parameters` turns it into
per-heliostat physical parameters (random phases, directions, dates), recorded in truth.json.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EffectSpec:
    unit: str
    default: float
    driver: str
    in_library: bool
    description: str


EFFECTS: dict[str, EffectSpec] = {
    "none": EffectSpec("-", 0.0, "-", True, "no hidden effect (null suite)"),
    "actuator_geometry": EffectSpec(
        "relative pivot_radius error",
        0.015,
        "axis counts",
        True,
        "true pivot_radius = (1 + a) x file value on both actuators, offset = (1 - a/2) x file value",
    ),
    "backlash": EffectSpec(
        "mrad of joint angle (half backlash)",
        0.3,
        "approach direction",
        True,
        "stroke lost on reversal: true stroke = commanded - direction x L/2, L set from a and the local slope",
    ),
    "thermal": EffectSpec(
        "1/K stroke expansion",
        5e-5,
        "temperature",
        True,
        "true stroke = stroke x (1 + a (T - 20 C)) on both actuators (T from the weather row)",
    ),
    "wind": EffectSpec(
        "mrad of mirror normal at 10 m/s",
        0.5,
        "wind speed",
        True,
        "wind pressure droops the mirror normal toward the horizon by a (v / 10 m/s)^2",
    ),
    "clock": EffectSpec(
        "seconds of controller clock offset",
        10.0,
        "time",
        True,
        "controller time = t + a + a x (t - t0) / 100 days: the sun is computed at the wrong time",
    ),
    "encoder_wobble": EffectSpec(
        "mrad of axis-2 joint angle",
        0.3,
        "axis-2 angle",
        True,
        "2-per-revolution bearing wobble: theta2 += a sin(2 theta2 + phase)",
    ),
    "gravity_sag": EffectSpec(
        "mrad of mirror normal",
        1.0,
        "normal elevation",
        True,
        "the mirror's weight tilts the normal down by a cos(elevation of the normal)",
    ),
    "refraction": EffectSpec(
        "fraction of standard refraction ignored",
        1.0,
        "sun elevation",
        True,
        "the light comes from the apparent sun, the controller aims with the geometric sun (a x refraction)",
    ),
    "survey_heliostat": EffectSpec(
        "metres of position error",
        0.1,
        "target geometry",
        True,
        "the true heliostat position differs from the properties file by a in a random 3-D direction",
    ),
    "survey_target": EffectSpec(
        "metres of target offset",
        0.1,
        "target",
        True,
        "each target's true centre differs from the tower file by a (random east/up direction)",
    ),
    "step": EffectSpec(
        "mrad of joint zero jump",
        1.0,
        "time",
        True,
        "maintenance: both joint zeros jump by a (random signs and split) at a random date per heliostat",
    ),
    "offset_drift": EffectSpec(
        "mrad of joint zero drift over the records",
        1.0,
        "time",
        True,
        "creep: both joint zeros drift linearly in time, by a (random split) over a heliostat's records",
    ),
    "wind_direction": EffectSpec(
        "mrad of axis-2 joint at 10 m/s",
        0.5,
        "wind direction",
        False,
        "wind yaw torque: theta2 += a (v / 10) sin(wind_from - mirror azimuth), linear in v",
    ),
    "lens_distortion": EffectSpec(
        "metres of barrel distortion at 1 m from the target centre",
        0.15,
        "spot position on target",
        False,
        "camera: measured offset from target centre r' = r (1 + k |r|^2), k = a / 1 m^3",
    ),
    "daily_periodic": EffectSpec(
        "mrad of mirror normal",
        0.5,
        "UTC time of day",
        False,
        "24-hour periodic tilt of the pylon: elevation of the normal += a sin(2 pi t / 1 day + phase)",
    ),
}


def draw_parameters(
    effect: str, amplitude: float, heliostats: list[str], times: dict[str, np.ndarray], rng: np.random.Generator
) -> dict:
    """Per-heliostat physical parameters of the effect (JSON-ready)."""
    if effect not in EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; choose from {sorted(EFFECTS)}")
    params: dict = {"amplitude": float(amplitude), "unit": EFFECTS[effect].unit, "per_heliostat": {}}
    if effect == "survey_target":
        targets = {}
        for name in ("solar_tower_juelich_lower", "solar_tower_juelich_upper", "multi_focus_tower"):
            ang = rng.uniform(0, 2 * np.pi)
            targets[name] = [float(amplitude * np.cos(ang)), 0.0, float(amplitude * np.sin(ang))]
        params["target_offsets_enu_m"] = targets
    for h in heliostats:
        p: dict = {}
        if effect == "encoder_wobble" or effect == "daily_periodic":
            p["phase_rad"] = float(rng.uniform(0, 2 * np.pi))
        elif effect == "survey_heliostat":
            v = rng.normal(size=3)
            p["offset_enu_m"] = (amplitude * v / np.linalg.norm(v)).tolist()
        elif effect == "offset_drift":
            t = np.asarray(times[h])
            p["start_unix"], p["end_unix"] = float(t.min()), float(t.max())
            ang = rng.uniform(0, 2 * np.pi)
            p["drift_axis_1_mrad"] = float(amplitude * np.cos(ang))
            p["drift_axis_2_mrad"] = float(amplitude * np.sin(ang))
        elif effect == "step":
            t = np.sort(times[h])
            lo, hi = t[len(t) // 4], t[(3 * len(t)) // 4]
            p["step_unix"] = float(rng.uniform(lo, hi))
            ang = rng.uniform(0, 2 * np.pi)
            p["jump_axis_1_mrad"] = float(amplitude * np.cos(ang))
            p["jump_axis_2_mrad"] = float(amplitude * np.sin(ang))
        params["per_heliostat"][h] = p
    return params


def stroke_change(effect, amplitude, stroke, axis, ctx, act) -> np.ndarray:
    """Physical change of the actuator stroke (m) for `axis` (0 or 1)."""
    if effect == "thermal":
        return stroke * amplitude * (ctx["temperature"] - 20.0)
    if effect == "backlash":
        h = 1e-6
        slope = np.abs(act.angle_from_stroke(stroke + h) - act.angle_from_stroke(stroke - h)) / (2 * h)
        half_loss = amplitude * 1e-3 / np.median(slope)
        return -ctx["direction"][:, axis] * half_loss
    return np.zeros_like(stroke)


def joint_change(effect, amplitude, theta1, theta2, ctx, hp) -> tuple[np.ndarray, np.ndarray]:
    """Physical change of the joint angles (rad)."""
    d1, d2 = np.zeros_like(theta1), np.zeros_like(theta2)
    if effect == "encoder_wobble":
        d2 = amplitude * 1e-3 * np.sin(2 * theta2 + hp["phase_rad"])
    elif effect == "step":
        after = ctx["time"] >= hp["step_unix"]
        d1 = np.where(after, hp["jump_axis_1_mrad"] * 1e-3, 0.0)
        d2 = np.where(after, hp["jump_axis_2_mrad"] * 1e-3, 0.0)
    elif effect == "offset_drift":
        frac = (ctx["time"] - hp["start_unix"]) / max(hp["end_unix"] - hp["start_unix"], 1.0)
        d1 = hp["drift_axis_1_mrad"] * 1e-3 * frac
        d2 = hp["drift_axis_2_mrad"] * 1e-3 * frac
    elif effect == "wind_direction":
        mirror_az = theta2  # 0 = facing south, positive toward east (compass 180 - theta2)
        facing_compass = np.pi - mirror_az
        wind_from = np.radians(ctx["wind_direction"])
        d2 = amplitude * 1e-3 * (ctx["wind_speed"] / 10.0) * np.sin(wind_from - facing_compass)
    return d1, d2


def normal_elevation_change(effect, amplitude, normal, ctx, hp) -> np.ndarray:
    """Rotation (rad) of the normal toward the zenith (negative = droop) about its horizontal axis."""
    if effect == "wind":
        return -amplitude * 1e-3 * (ctx["wind_speed"] / 10.0) ** 2
    if effect == "gravity_sag":
        return -amplitude * 1e-3 * np.sqrt(np.clip(1 - normal[:, 2] ** 2, 0, 1))
    if effect == "daily_periodic":
        return amplitude * 1e-3 * np.sin(2 * np.pi * ctx["time"] / 86400.0 + hp["phase_rad"])
    return np.zeros(normal.shape[0])


def camera_distortion(effect, amplitude, offset_in_plane) -> np.ndarray:
    """Measured in-plane offset (m) from the target centre, (n, 2)."""
    if effect == "lens_distortion":
        r2 = np.sum(offset_in_plane**2, axis=-1, keepdims=True)
        return offset_in_plane * (1.0 + amplitude * r2)
    return offset_in_plane
