"""Discovery from data on disk: a hidden-effect fleet written in the PAINT layout
(timestamps and the weather CSV) by a small writer of its own - plain json and csv,
as another program would - is read back by heliojax.load_paint_directory and
analysed by the ``heliojax discover`` command; and the real shared records."""

from __future__ import annotations

import csv
import datetime as dt
import json
import math
from pathlib import Path

import jax
import numpy as np
import pytest
from test_discovery import HELDOUT_BOUND, NOISE, H, M

import heliojax as hj
from heliojax.discovery import simulate_fleet
from heliojax.effects import make_effect

PLANT = [50.913421122592574, 6.387824755874856, 87.0]
TARGET = "solar_tower_juelich_lower"


def _lla(enu):
    return [float(x) for x in np.asarray(hj.enu_to_wgs84(np.asarray(enu, float), np.asarray(PLANT)))]


def _write_like_another_program(root: Path, fleet) -> None:
    """The PAINT download layout, written with json/csv only (no heliojax writer)."""
    root.mkdir(parents=True, exist_ok=True)
    tg = hj.calibration_target()
    c, u, v = (np.asarray(x) for x in (tg.centre, tg.u_axis, tg.v_axis))
    hw, hh = float(tg.half_width), float(tg.half_height)
    corners = {
        "upper_left": c - hw * u + hh * v,
        "upper_right": c + hw * u + hh * v,
        "lower_left": c - hw * u - hh * v,
        "lower_right": c + hw * u - hh * v,
    }
    tower = {
        "power_plant_properties": {"ID": "WRI1030197", "coordinates": PLANT},
        TARGET: {
            "type": "planar",
            "normal_vector": [0, 1, 0],
            "coordinates": {"center": _lla(c), **{k: _lla(p) for k, p in corners.items()}},
        },
    }
    (root / "WRI1030197-tower-measurements.json").write_text(json.dumps(tower, indent=1))
    g = fleet.geometry
    act = g.actuators
    timestamps = {}
    rows = []
    # numpy copies up front: indexing a JAX array with Python ints in the loops below
    # compiled a program per index (thousands of them)
    ctx = jax.tree.map(np.asarray, fleet.context)
    sun = ctx.sun
    record_id, fleet_counts = np.asarray(fleet.record_id), np.asarray(fleet.counts)
    act = jax.tree.map(np.asarray, act)
    spots = np.asarray(hj.enu_to_wgs84(np.asarray(fleet.focal_spot), np.asarray(PLANT)))
    centre_lla = _lla(c)
    positions = np.asarray(hj.enu_to_wgs84(np.asarray(g.position), np.asarray(PLANT)))
    for i, hid in enumerate(fleet.ids):
        props = {
            "heliostat_position": [float(x) for x in positions[i]],
            "height": 2.56,
            "width": 3.22,
            "initial_orientation": [0.0, -1.0, 0.0],
            "kinematics_properties": {
                "actuators": [
                    {
                        "type_axis": "linear",
                        "min_increment": int(act.min_counts[i, a]),
                        "max_increment": int(act.max_counts[i, a]),
                        "increment": float(act.increment[i, a]),
                        "initial_stroke_length": float(act.initial_stroke_length[i, a]),
                        "offset": float(act.offset[i, a]),
                        "pivot_radius": float(act.pivot_radius[i, a]),
                        "clockwise_axis_movement": 0 if float(act.sign[i, a]) > 0 else 1,
                        "initial_angle": float(act.initial_angle[i, a]),
                    }
                    for a in range(2)
                ],
                **{f"joint_translation_{k}_{n}": 0.0 for n in (1, 2) for k in "enu"},
                **{
                    f"concentrator_translation_{k}": float(x)
                    for k, x in zip("enu", np.asarray(g.concentrator_translation)[i])
                },
            },
        }
        (root / hid / "Properties").mkdir(parents=True)
        (root / hid / "Calibration").mkdir(parents=True)
        (root / hid / "Properties" / f"{hid}-heliostat-properties.json").write_text(json.dumps(props))
        for j in range(fleet.n_records):
            rid = int(record_id[i, j])
            s = sun[i, j]
            az = math.degrees(math.atan2(s[0], -s[1]))
            el = math.degrees(math.asin(s[2]))
            spot = [float(x) for x in spots[i, j]]
            counts = [int(round(float(x))) for x in fleet_counts[i, j]]
            rec = {
                "motor_position": {"axis_1_motor_position": counts[0], "axis_2_motor_position": counts[1]},
                "target_name": TARGET,
                "sun_elevation": el,
                "sun_azimuth": az,
                "focal_spot": {"HeliOS": spot, "UTIS": spot},
            }
            (root / hid / "Calibration" / f"{rid}-calibration-properties.json").write_text(json.dumps(rec))
            when = dt.datetime.fromtimestamp(float(ctx.unix_time[i, j]), dt.UTC)
            stamp = when.strftime("%Y-%m-%dT%H:%M:%SZ")
            timestamps[str(rid)] = {"heliostat_id": hid, "datetime": stamp}
            rows.append(
                {
                    "heliostat_id": hid,
                    "timestamp": stamp,
                    "sample_id": rid,
                    "sun_elevation": el,
                    "sun_azimuth": az,
                    "axis_1_motor_position": counts[0],
                    "axis_2_motor_position": counts[1],
                    "target_name": TARGET,
                    "heliostat_lat": props["heliostat_position"][0],
                    "heliostat_lon": props["heliostat_position"][1],
                    "heliostat_alt": props["heliostat_position"][2],
                    "focal_spot_lat": spot[0],
                    "focal_spot_lon": spot[1],
                    "focal_spot_alt": spot[2],
                    "target_center_lat": centre_lla[0],
                    "target_center_lon": centre_lla[1],
                    "target_center_alt": centre_lla[2],
                    "tracking_error_lat": "",
                    "tracking_error_lon": "",
                    "tracking_error_alt": "",
                    "wind_speed": f"{float(ctx.wind_speed[i, j]):.4f}",
                    "wind_direction": f"{math.degrees(float(ctx.wind_direction[i, j])):.4f}",
                    "dni": "800.0",
                    "temperature": f"{float(ctx.temperature[i, j]):.4f}",
                    "humidity": "40.0",
                    "pressure": "1005.0",
                }
            )
    (root / "calibration-timestamps.json").write_text(json.dumps(timestamps, indent=1))
    with open(root / "calibration-with-weather.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


@pytest.fixture(scope="module")
def paint_dir(tmp_path_factory):
    # Whole-second times: the PAINT timestamps have a resolution of 1 s.
    true = [
        make_effect("backlash", backlash_1=3e-4, backlash_2=3e-4),
        make_effect("thermal", thermal_1=1.5e-5, thermal_2=1.5e-5, thermal_reference_c=10.0),
    ]
    fleet, _ = simulate_fleet(105, H, M, effects=true, noise_mrad=NOISE)
    root = tmp_path_factory.mktemp("paint")
    _write_like_another_program(root, fleet)
    return root, fleet


def test_written_data_read_back_like_the_simulation(paint_dir):
    root, fleet = paint_dir
    loaded = hj.load_paint_directory(root)
    assert loaded.ids == fleet.ids
    order = np.argsort(np.asarray(fleet.context.unix_time), axis=1)  # the loader sorts by time
    np.testing.assert_allclose(
        np.asarray(loaded.context.approach), np.take_along_axis(np.asarray(fleet.context.approach), order[..., None], 1)
    )
    np.testing.assert_allclose(
        np.asarray(loaded.context.temperature),
        np.take_along_axis(np.asarray(fleet.context.temperature), order, 1),
        atol=1e-4,
    )


def test_discover_command_on_paint_layout(paint_dir, tmp_path):
    """``heliojax discover`` on the written fleet names its two hidden effects
    (backlash and thermal) and reaches the held-out bound of tests/test_discovery.py
    (this run is also that file's two-hidden-effects case)."""
    from heliojax.cli._main import main

    root, _ = paint_dir
    report, figs, md = tmp_path / "report.json", tmp_path / "figs", tmp_path / "summary.md"
    rc = main(
        [
            "discover",
            str(root),
            "--base",
            "stone8",
            "--report",
            str(report),
            "--figures",
            str(figs),
            "--markdown",
            str(md),
            "--cache-dir",
            "none",
            "--quiet",
        ]
    )
    assert rc == 0
    r = json.loads(report.read_text())
    for key in (
        "base_model",
        "steps",
        "named_effects",
        "not_identifiable",
        "heldout_rms_base_mrad",
        "heldout_rms_final_mrad",
    ):
        assert key in r
    assert r["base_model"] == "stone8"
    assert r["config"]["effect_prior"] is True
    assert set(r["named_effects"][:2]) == {"backlash", "thermal"}
    for s in r["steps"]:
        for key in (
            "effect",
            "delta_bic",
            "cv_heldout_rms_before_mrad",
            "cv_heldout_rms_after_mrad",
            "amplitude",
            "heliostats",
        ):
            assert key in s
        assert (
            s["delta_bic"] > r["config"]["min_delta_bic"]
            and s["cv_heldout_rms_after_mrad"] < s["cv_heldout_rms_before_mrad"]
        )
    assert r["heldout_rms_final_mrad"] < r["heldout_rms_base_mrad"]
    assert r["heldout_rms_final_mrad"] <= HELDOUT_BOUND
    pngs = sorted(p.name for p in figs.glob("*.png"))
    assert "heldout_per_step.png" in pngs and any(p.startswith("residuals_step1_") for p in pngs)
    assert all((figs / p).read_bytes()[:4] == b"\x89PNG" for p in pngs)
    assert "backlash" in md.read_text() and "# Discovery report" in md.read_text()


def test_discover_command_rejects_unknown_effect(tmp_path, capsys):
    from heliojax.cli._main import main

    rc = main(["discover", "--effects", "backlash,magnetism", "--report", str(tmp_path / "r.json")])
    assert rc == 2
    assert "magnetism" in capsys.readouterr().err
