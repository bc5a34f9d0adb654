"""Checks of the simulator against the real PAINT records (sun positions, nominal pointing)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ._paintio import (
    TIMES_FILE,
    parse_utc,
    properties_path,
    read_mount,
    read_records,
    read_tower,
)
from ._solar import refraction_deg, sun_compass, to_paint_azimuth


def compare_sun_with_records(source) -> dict:
    """Own sun positions vs the sun_azimuth / sun_elevation stored in every timestamped real record.

    Returns median and 99th-percentile absolute differences in degrees (azimuth, apparent elevation with
    refraction, geometric elevation) and the number of records compared.
    """
    root = Path(source)
    _tower, _frame, _targets = read_tower(root)
    stamps = json.loads((root / TIMES_FILE).read_text())
    daz, del_app, del_geo = [], [], []
    for hdir in sorted(p for p in root.iterdir() if (p / "Calibration").is_dir()):
        site = None
        if properties_path(root, hdir.name).exists():
            site = json.loads(properties_path(root, hdir.name).read_text())["heliostat_position"]
        for rid, rec in read_records(root, hdir.name).items():
            if rid not in stamps:
                continue
            lat, lon = (site[0], site[1]) if site else (50.9134, 6.3878)
            az, el = sun_compass(parse_utc(stamps[rid]["datetime"]), lat, lon)
            daz.append((float(to_paint_azimuth(az)) - rec["sun_azimuth"] + 180.0) % 360.0 - 180.0)
            del_app.append(float(el + refraction_deg(el)) - rec["sun_elevation"])
            del_geo.append(float(el) - rec["sun_elevation"])
    a, e, g = (np.abs(np.array(x)) for x in (daz, del_app, del_geo))
    return {
        "n_records": int(a.size),
        "azimuth_median_deg": float(np.median(a)),
        "azimuth_p99_deg": float(np.percentile(a, 99)),
        "elevation_median_deg": float(np.median(e)),
        "elevation_p99_deg": float(np.percentile(e, 99)),
        "elevation_without_refraction_median_deg": float(np.median(g)),
    }


def nominal_normal_errors(source) -> np.ndarray:
    """Angle (mrad) between the nominal model's mirror normal from the counts and the normal implied by
    each real record (bisector of the recorded sun and the direction to the HeliOS spot)."""
    root = Path(source)
    _tower, frame, _targets = read_tower(root)
    out = []
    for hdir in sorted(p for p in root.iterdir() if properties_path(root, p.name).exists()):
        _raw, mount = read_mount(root, hdir.name, frame)
        for rec in read_records(root, hdir.name).values():
            az, el = np.radians(rec["sun_azimuth"]), np.radians(rec["sun_elevation"])
            sun = np.array([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)])
            c = rec["motor_position"]
            normal, centre = mount.pose(
                mount.act1.angle(c["axis_1_motor_position"]), mount.act2.angle(c["axis_2_motor_position"])
            )
            d = frame.to_enu(rec["focal_spot"]["HeliOS"]) - centre
            bis = sun + d / np.linalg.norm(d)
            bis = bis / np.linalg.norm(bis)
            out.append(float(np.arccos(np.clip(normal @ bis, -1.0, 1.0))) * 1e3)
    return np.array(out)
