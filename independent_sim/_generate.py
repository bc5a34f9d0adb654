"""Generate a PAINT-layout calibration suite with one hidden effect (see README.md for conventions)."""

from __future__ import annotations

import csv
import json
import shutil
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

from . import _effects as fx
from ._mount import Mount, aim_normal, hit_plane, reflect, small_rotation
from ._paintio import (
    CSV_FILE,
    TIMES_FILE,
    TOWER_FILE,
    format_utc,
    parse_utc,
    properties_path,
    read_mount,
    read_records,
    read_tower,
    read_weather,
    write_record,
)
from ._solar import refraction_deg, sun_compass, sun_vector_enu, to_paint_azimuth

DEFAULT_SOURCE = Path("/work/shared/data/paint")
ANOMALOUS = {"BF41"}  # properties file with implausible actuator values (see the PAINT README)
WEATHER = ("wind_speed", "wind_direction", "dni", "temperature", "humidity", "pressure")


def _plane_axes(normal):
    a1 = np.cross([0.0, 0.0, 1.0], normal)
    if np.linalg.norm(a1) < 1e-9:
        a1 = np.array([1.0, 0.0, 0.0])
    a1 = a1 / np.linalg.norm(a1)
    return a1, np.cross(normal, a1)


def _pick_heliostats(root: Path, n: int) -> list[str]:
    have = [p.name for p in sorted(root.iterdir()) if properties_path(root, p.name).exists()]
    have = [h for h in have if h not in ANOMALOUS]
    counts = {h: len(list((root / h / "Calibration").glob("*.json"))) for h in have}
    chosen = sorted(have, key=lambda h: (-counts[h], h))[:n]
    if len(chosen) < n:
        raise ValueError(f"only {len(chosen)} usable heliostats with properties in {root}")
    return sorted(chosen)


def _weather_table(rows: list[dict]):
    """Rows with complete weather, without long forward-filled repeats; arrays for nearest matching."""

    def key(r):
        return tuple(r.get(c, "") for c in WEATHER)

    rep = Counter(key(r) for r in rows)
    good = [r for r in rows if all(r.get(c) for c in WEATHER) and r.get("timestamp") and rep[key(r)] <= 20]
    unix = np.array([parse_utc(r["timestamp"]) for r in good])
    return good, unix


def _match_weather(unix_rec: float, good_unix: np.ndarray, used: np.ndarray) -> int:
    """Nearest unused weather row by day of year and time of day (each row used once)."""
    doy = lambda u: (u / 86400.0) % 365.2425
    dd = np.abs(doy(good_unix) - doy(unix_rec))
    dd = np.minimum(dd, 365.2425 - dd)
    dh = np.abs((good_unix % 86400.0) - (unix_rec % 86400.0)) / 3600.0
    i = int(np.argmin(dd / 30.0 + dh / 2.0 + 1e9 * used))
    used[i] = True
    return i


def _apply_plant(nominal: Mount, info: dict) -> Mount:
    scale = info["increment_scale"]
    return nominal.with_changes(
        base_q=small_rotation(info["base_rotvec_rad"]),
        between_q=small_rotation(info["between_axes_rotvec_rad"]),
        mirror_q=small_rotation(info["mirror_rotvec_rad"]),
        zero_1=float(info["joint_zero_offsets_rad"][0]),
        zero_2=float(info["joint_zero_offsets_rad"][1]),
        act1=replace(nominal.act1, increment=nominal.act1.increment * scale[0]),
        act2=replace(nominal.act2, increment=nominal.act2.increment * scale[1]),
    )


def plant_mount(suite_dir, heliostat: str) -> Mount:
    """The true plant of `heliostat` in a written suite (its properties file + truth.json's plant state)."""
    root = Path(suite_dir)
    truth = json.loads((root / "truth.json").read_text())
    _tower, frame, _targets = read_tower(root)
    _raw, nominal = read_mount(root, heliostat, frame)
    return _apply_plant(nominal, truth["heliostats"][heliostat]["plant"])


def _draw_plant(nominal: Mount, rng: np.random.Generator, size: float) -> tuple[Mount, dict]:
    base = rng.normal(0, 3e-3 * size, 3)
    between = rng.normal(0, 1e-3 * size, 3)
    mirror = rng.normal(0, 2e-3 * size, 3)
    zeros = rng.normal(0, 5e-3 * size, 2)
    scale = 1.0 + rng.normal(0, 3e-3 * size, 2)
    info = {
        "base_rotvec_rad": base.tolist(),
        "between_axes_rotvec_rad": between.tolist(),
        "mirror_rotvec_rad": mirror.tolist(),
        "joint_zero_offsets_rad": zeros.tolist(),
        "increment_scale": scale.tolist(),
    }
    return _apply_plant(nominal, info), info


def _feasible(recs, raw: dict, controller: Mount, targets, margin: int = 600) -> np.ndarray:
    """Whether the controller can reach each record's target centre within the actuators' count range."""
    if not recs:
        return np.zeros(0, dtype=bool)
    site = raw["heliostat_position"]
    t = np.array([r[1] for r in recs])
    az, el = sun_compass(t, site[0], site[1])
    sun = sun_vector_enu(az, el + refraction_deg(el))
    aim = np.stack([targets[r[2]][0] for r in recs])
    th1, th2 = aim_normal(controller, sun, aim)
    ok = np.ones(len(recs), dtype=bool)
    for act, counts in zip(
        raw["kinematics_properties"]["actuators"], (controller.act1.counts(th1), controller.act2.counts(th2))
    ):
        ok &= (counts > act["min_increment"] + margin) & (counts < act["max_increment"] - margin)
    return ok & (el > 3.0)


def _simulate(effect, amp, hp, plant: Mount, controller: Mount, site, ctx, aim, targets_file, targets_true):
    """Counts, noise-free measured spots (ENU), mirror centres, approach directions and
    what the plant records (its clock's unix time, the sun's compass azimuth and
    elevation in deg as the controller computes them) of one heliostat's records
    under `effect`. A plant stamps its records with the controller's clock and stores
    the sun the controller aimed with: a clock or refraction error of the controller
    reaches the records, not only the counts it chose."""
    t = ctx["time"]
    az, el = sun_compass(t, site[0], site[1])
    light = sun_vector_enu(az, el + refraction_deg(el))
    t_ctrl = t + (amp + amp * (t - ctx["t0"]) / (100 * 86400.0) if effect == "clock" else 0.0)
    az_c, el_c = sun_compass(t_ctrl, site[0], site[1])
    ignored = amp if effect == "refraction" else 0.0
    sun_ctrl = sun_vector_enu(az_c, el_c + (1.0 - ignored) * refraction_deg(el_c))
    th1, th2 = aim_normal(controller, sun_ctrl, aim)
    counts = np.stack([np.rint(controller.act1.counts(th1)), np.rint(controller.act2.counts(th2))], -1)
    true = plant
    if effect == "actuator_geometry":
        true = plant.with_changes(
            **{
                k: replace(a, pivot=a.pivot * (1 + amp), offset=a.offset * (1 - amp / 2))
                for k, a in (("act1", plant.act1), ("act2", plant.act2))
            }
        )
    if effect == "survey_heliostat":
        true = true.with_changes(position=plant.position + np.asarray(hp["offset_enu_m"]))
    d = np.sign(np.diff(counts, axis=0))
    direction = np.vstack([ctx["first_direction"], d])
    for i in range(1, len(direction)):  # an axis that did not move keeps its last approach direction
        direction[i] = np.where(direction[i] == 0, direction[i - 1], direction[i])
    ctx = dict(ctx, direction=direction)
    strokes = []
    for axis, act in enumerate((true.act1, true.act2)):
        s = act.stroke(counts[:, axis])
        strokes.append(s + fx.stroke_change(effect, amp, s, axis, ctx, act))
    j1, j2 = true.act1.angle_from_stroke(strokes[0]), true.act2.angle_from_stroke(strokes[1])
    dj1, dj2 = fx.joint_change(effect, amp, j1, j2, ctx, hp)
    normal, centre = true.pose(j1 + dj1, j2 + dj2)
    tilt = fx.normal_elevation_change(effect, amp, normal, ctx, hp)
    up_perp = np.array([0.0, 0.0, 1.0]) - normal[:, 2:3] * normal
    up_perp = up_perp / np.linalg.norm(up_perp, axis=-1, keepdims=True)
    normal = normal * np.cos(tilt)[:, None] + up_perp * np.sin(tilt)[:, None]
    beam = reflect(light, normal)
    spots = np.empty_like(centre)
    for i, name in enumerate(ctx["target"]):
        c_file, n_t = targets_file[name]
        c_true = targets_true[name]
        hit = hit_plane(centre[i], beam[i], c_true, n_t)
        a1, a2 = _plane_axes(n_t)
        off = fx.camera_distortion(effect, amp, np.array([[(hit - c_true) @ a1, (hit - c_true) @ a2]]))[0]
        spots[i] = c_file + off[0] * a1 + off[1] * a2
    recorded = {"time": t_ctrl, "azimuth": az_c, "elevation": el_c + (1.0 - ignored) * refraction_deg(el_c)}
    return counts.astype(np.int64), spots, centre, direction, recorded


NOISE_KINDS = ("gaussian", "student_t", "heteroscedastic", "daily")
HETEROSCEDASTIC_RANGE = 2.0  # a heliostat's noise scale within 1/2 to 2 times the suite's


def _noise_of_kind(kind: str, normal: np.ndarray, unix_time: np.ndarray, rng) -> np.ndarray:
    """Unit noise of one heliostat's records, shape (n, 2), of the law `kind` (see `generate`)."""
    n = normal.shape[0]
    if kind == "student_t":
        dof = 3.0
        return rng.standard_t(dof, (n, 2)) / np.sqrt(dof / (dof - 2.0))
    if kind == "heteroscedastic":
        lo, hi = -np.log(HETEROSCEDASTIC_RANGE), np.log(HETEROSCEDASTIC_RANGE)
        scale = np.exp(rng.uniform(lo, hi))
        mean_variance = (HETEROSCEDASTIC_RANGE**2 - HETEROSCEDASTIC_RANGE**-2) / (4 * np.log(HETEROSCEDASTIC_RANGE))
        return normal * scale / np.sqrt(mean_variance)
    day = np.floor(np.asarray(unix_time) / 86400.0).astype(np.int64)
    _, index = np.unique(day, return_inverse=True)
    shared = rng.normal(0, 1, (int(index.max()) + 1, 2))
    return np.sqrt(0.5) * normal + np.sqrt(0.5) * shared[index]


def generate(
    effect: str,
    out_dir,
    seed: int = 0,
    amplitude: float | None = None,
    n_heliostats: int = 20,
    n_records: int = 60,
    noise_mrad: float = 0.25,
    outliers: float = 0.0,
    controller: str = "calibrated",
    aim_spread_m: float = 0.8,
    plant_errors: float = 1.0,
    source=DEFAULT_SOURCE,
    noise_kind: str = "gaussian",
) -> dict:
    """Write a PAINT-layout suite to `out_dir` and return the truth (also written as truth.json).

    effect: a key of `EFFECTS`; amplitude in the effect's unit (default `EFFECTS[effect].default`);
    noise_mrad: camera centroid noise per in-plane component as beam angle (mrad); outliers: fraction of
    records displaced by 10-100 mrad; controller: 'calibrated' (knows the plant without the hidden effect)
    or 'nominal' (aims with the properties files); aim_spread_m: half-width of the controller's aim points
    around each target centre (m); plant_errors: scale of the drawn plant state (0 = the nominal plant).
    noise_kind: the camera noise's law, each with standard deviation `noise_mrad` per component on average:
    'gaussian' (independent normal), 'student_t' (independent Student t with 3 degrees of freedom: heavy
    tails short of gross errors), 'heteroscedastic' (normal, each heliostat's own scale drawn log-uniformly
    within 1/2 to 2 times, normalised to a mean variance of `noise_mrad`^2) or 'daily' (normal, half of the
    variance shared by the records of one heliostat on one day: the target's or the camera's state of
    that day).
    """
    if effect not in fx.EFFECTS:
        raise ValueError(f"unknown effect {effect!r}; choose from {sorted(fx.EFFECTS)}")
    if controller not in ("calibrated", "nominal"):
        raise ValueError("controller must be 'calibrated' or 'nominal'")
    if noise_kind not in NOISE_KINDS:
        raise ValueError(f"unknown noise_kind {noise_kind!r}; choose from {NOISE_KINDS}")
    amp = float(fx.EFFECTS[effect].default if amplitude is None else amplitude)
    root, out = Path(source), Path(out_dir)
    rng = np.random.default_rng(seed)
    tower, frame, targets = read_tower(root)
    stamps = json.loads((root / TIMES_FILE).read_text())
    fields, rows = read_weather(root)
    by_sample = {r["sample_id"]: r for r in rows if all(r.get(c) for c in WEATHER)}
    good, good_unix = _weather_table(rows)
    used = np.array([r["sample_id"] in by_sample for r in good])
    heliostats = _pick_heliostats(root, n_heliostats)
    pool = []  # (time, target) of every real timestamped record of any heliostat
    own: dict[str, list] = {}
    for hdir in sorted(p for p in root.iterdir() if (p / "Calibration").is_dir()):
        for rid, rec in read_records(root, hdir.name).items():
            if rid in stamps and rec.get("target_name") in targets:
                item = (rid, parse_utc(stamps[rid]["datetime"]), rec["target_name"])
                pool.append((hdir.name,) + item)
                own.setdefault(hdir.name, []).append(item)
    next_id = 9_000_000
    plan: dict[str, list] = {}
    plants: dict[str, tuple] = {}
    for h in heliostats:
        raw, nominal = read_mount(root, h, frame)
        plant, plant_info = _draw_plant(nominal, rng, plant_errors)
        plants[h] = (raw, nominal, plant, plant_info)
        ctrl = plant if controller == "calibrated" else nominal
        mine = own.get(h, [])
        others = [p for p in pool if p[0] != h]
        extra = []
        for j in rng.choice(len(others), min(len(others), n_records + 40), replace=False):
            extra.append((str(next_id), others[j][2], others[j][3]))
            next_id += 1
        ok_mine = _feasible(mine, raw, ctrl, targets)
        ok_extra = _feasible(extra, raw, ctrl, targets)
        mine = [r for r, ok in zip(mine, ok_mine) if ok]
        if len(mine) > n_records:
            mine = [mine[i] for i in sorted(rng.choice(len(mine), n_records, replace=False))]
        extra = [r for r, ok in zip(extra, ok_extra) if ok][: n_records - len(mine)]
        if len(mine) + len(extra) < n_records:
            raise ValueError(f"{h}: only {len(mine) + len(extra)} reachable records")
        plan[h] = sorted(mine + extra, key=lambda x: x[1])
    times = {h: np.array([r[1] for r in plan[h]]) for h in heliostats}
    params = fx.draw_parameters(effect, amp, heliostats, times, rng)
    targets_true = {
        k: v[0] + np.asarray(params.get("target_offsets_enu_m", {}).get(k, [0.0, 0, 0])) for k, v in targets.items()
    }
    targets_nominal = {k: v[0] for k, v in targets.items()}
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    shutil.copyfile(root / TOWER_FILE, out / TOWER_FILE)
    csv_rows, stamps_out = [], {}
    truth = {
        "effect": effect,
        "in_library": fx.EFFECTS[effect].in_library,
        "driver": fx.EFFECTS[effect].driver,
        "description": fx.EFFECTS[effect].description,
        "parameters": params,
        "seed": seed,
        "noise_mrad": noise_mrad,
        "noise_kind": noise_kind,
        "outlier_fraction": outliers,
        "controller": controller,
        "source": str(root),
        "heliostats": {},
        "outliers": [],
        "steps": [],
    }
    all_dev = []
    for h in heliostats:
        raw, nominal, plant, plant_info = plants[h]
        recs = plan[h]
        n = len(recs)
        wrows = [by_sample.get(r[0]) or good[_match_weather(r[1], good_unix, used)] for r in recs]
        aim_off = rng.uniform(-aim_spread_m, aim_spread_m, (n, 2))
        first_dir = rng.choice([-1.0, 1.0], 2)
        noise = rng.normal(0, 1, (n, 2))
        if noise_kind != "gaussian":  # drawn after the default draws, so 'gaussian' suites stay as they were
            noise = _noise_of_kind(noise_kind, noise, times[h], rng)
        is_out = rng.random(n) < outliers
        out_ang, out_dir_ang = rng.uniform(10e-3, 100e-3, n), rng.uniform(0, 2 * np.pi, n)
        aim = np.empty((n, 3))
        for i, r in enumerate(recs):
            a1, a2 = _plane_axes(targets[r[2]][1])
            aim[i] = targets[r[2]][0] + aim_off[i, 0] * a1 + aim_off[i, 1] * a2
        ctx = {
            "time": times[h],
            "t0": float(times[h][0]),
            "target": [r[2] for r in recs],
            "temperature": np.array([float(w["temperature"]) for w in wrows]),
            "wind_speed": np.array([float(w["wind_speed"]) for w in wrows]),
            "wind_direction": np.array([float(w["wind_direction"]) for w in wrows]),
            "first_direction": first_dir,
        }
        ctrl = plant if controller == "calibrated" else nominal
        site = raw["heliostat_position"]
        hp = params["per_heliostat"][h]
        counts, spots, centre, direction, recorded = _simulate(
            effect, amp, hp, plant, ctrl, site, ctx, aim, targets, targets_true
        )
        spots0 = _simulate("none", 0.0, hp, plant, ctrl, site, ctx, aim, targets, targets_nominal)[1]
        dist = np.linalg.norm(spots - centre, axis=-1)
        all_dev.append(np.linalg.norm(spots - spots0, axis=-1) / dist * 1e3)
        (out / h / "Properties").mkdir(parents=True)
        (out / h / "Calibration").mkdir(parents=True)
        shutil.copyfile(properties_path(root, h), properties_path(out, h))
        az, el_app, stamp = recorded["azimuth"], recorded["elevation"], recorded["time"]
        for i, r in enumerate(recs):
            a1, a2 = _plane_axes(targets[r[2]][1])
            spot = spots[i] + noise_mrad * 1e-3 * dist[i] * (noise[i, 0] * a1 + noise[i, 1] * a2)
            if is_out[i]:
                spot = spot + out_ang[i] * dist[i] * (np.cos(out_dir_ang[i]) * a1 + np.sin(out_dir_ang[i]) * a2)
                truth["outliers"].append(
                    {"heliostat": h, "record_id": r[0], "displacement_mrad": float(out_ang[i] * 1e3)}
                )
            lla = frame.to_lla(spot)
            write_record(
                out / h / "Calibration" / f"{r[0]}-calibration-properties.json",
                counts[i],
                r[2],
                float(el_app[i]),
                float(to_paint_azimuth(az[i])),
                lla,
            )
            stamps_out[r[0]] = {"heliostat_id": h, "datetime": format_utc(float(stamp[i]))}
            centre_lla = tower[r[2]]["coordinates"]["center"]
            row = {
                "heliostat_id": h,
                "timestamp": format_utc(float(stamp[i])),
                "sample_id": r[0],
                "sun_elevation": float(el_app[i]),
                "sun_azimuth": float(to_paint_azimuth(az[i])),
                "axis_1_motor_position": int(counts[i, 0]),
                "axis_2_motor_position": int(counts[i, 1]),
                "target_name": r[2],
                "heliostat_lat": site[0],
                "heliostat_lon": site[1],
                "heliostat_alt": site[2],
                "focal_spot_lat": lla[0],
                "focal_spot_lon": lla[1],
                "focal_spot_alt": lla[2],
                "target_center_lat": centre_lla[0],
                "target_center_lon": centre_lla[1],
                "target_center_alt": centre_lla[2],
                "tracking_error_lat": lla[0] - centre_lla[0],
                "tracking_error_lon": lla[1] - centre_lla[1],
                "tracking_error_alt": lla[2] - centre_lla[2],
            }
            row.update({c: wrows[i][c] for c in WEATHER})
            csv_rows.append(row)
        if effect == "step":
            truth["steps"].append(
                {
                    "heliostat": h,
                    "time": format_utc(hp["step_unix"]),
                    "jump_mrad": {"axis_1": hp["jump_axis_1_mrad"], "axis_2": hp["jump_axis_2_mrad"]},
                }
            )
        truth["heliostats"][h] = {
            "plant": plant_info,
            "record_ids": [r[0] for r in recs],
            "reused_real_records": sum(1 for r in recs if int(r[0]) < 9_000_000),
            "approach_reversals": int(np.sum(np.abs(np.diff(direction, axis=0)) > 0)),
        }
    dev = np.concatenate(all_dev)
    truth["beam_rms_mrad"] = float(np.sqrt(np.mean(dev**2)))
    truth["beam_rms_per_component_mrad"] = truth["beam_rms_mrad"] / np.sqrt(2.0)
    (out / TIMES_FILE).write_text(json.dumps(stamps_out, indent=1))
    with open(out / CSV_FILE, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(csv_rows)
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth
