"""Reading and writing PAINT's download layout (tower, properties, calibration records, CSV)."""

from __future__ import annotations

import csv
import datetime as dt
import json
from pathlib import Path

import numpy as np

from ._geodesy import LocalFrame
from ._mount import Actuator, Mount

TOWER_FILE = "WRI1030197-tower-measurements.json"
CSV_FILE = "calibration-with-weather.csv"
TIMES_FILE = "calibration-timestamps.json"


def parse_utc(text: str) -> float:
    """ISO time 'YYYY-MM-DDTHH:MM:SSZ' -> unix seconds."""
    return dt.datetime.strptime(text, "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=dt.UTC).timestamp()


def format_utc(unix: float) -> str:
    return dt.datetime.fromtimestamp(round(unix), tz=dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def read_tower(root: Path):
    """Return (tower dict, LocalFrame at power_plant_properties.coordinates, {target: (centre ENU, normal)})."""
    tower = json.loads((root / TOWER_FILE).read_text())
    frame = LocalFrame(tower["power_plant_properties"]["coordinates"])
    targets = {}
    for name, item in tower.items():
        if isinstance(item, dict) and item.get("type") == "planar":
            centre = frame.to_enu(item["coordinates"]["center"])
            normal = np.asarray(item["normal_vector"], dtype=float)
            targets[name] = (centre, normal / np.linalg.norm(normal))
    return tower, frame, targets


def properties_path(root: Path, heliostat: str) -> Path:
    return root / heliostat / "Properties" / f"{heliostat}-heliostat-properties.json"


def read_mount(root: Path, heliostat: str, frame: LocalFrame) -> tuple[dict, Mount]:
    """Nominal mount from a properties file (raw dict returned too, to copy unchanged)."""
    raw = json.loads(properties_path(root, heliostat).read_text())
    kin = raw["kinematics_properties"]
    acts = [
        Actuator(
            increment=float(a["increment"]),
            initial_stroke=float(a["initial_stroke_length"]),
            offset=float(a["offset"]),
            pivot=float(a["pivot_radius"]),
            initial_angle=float(a["initial_angle"]),
            clockwise=bool(a["clockwise_axis_movement"]),
        )
        for a in kin["actuators"]
    ]
    j2 = np.array([kin["joint_translation_e_2"], kin["joint_translation_n_2"], kin["joint_translation_u_2"]])
    j1 = np.array([kin["joint_translation_e_1"], kin["joint_translation_n_1"], kin["joint_translation_u_1"]])
    mirror = np.array(
        [kin["concentrator_translation_e"], kin["concentrator_translation_n"], kin["concentrator_translation_u"]]
    )
    rest = np.asarray(raw["initial_orientation"], dtype=float)
    mount = Mount(
        position=frame.to_enu(raw["heliostat_position"]) + j1,
        act1=acts[0],
        act2=acts[1],
        rest_normal=rest / np.linalg.norm(rest),
        joint2_translation=j2,
        mirror_translation=mirror,
    )
    return raw, mount


def read_records(root: Path, heliostat: str) -> dict[str, dict]:
    out = {}
    for path in sorted((root / heliostat / "Calibration").glob("*-calibration-properties.json")):
        out[path.name.split("-")[0]] = json.loads(path.read_text())
    return out


def read_weather(root: Path) -> tuple[list[str], list[dict]]:
    with open(root / CSV_FILE, newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def write_record(path: Path, counts, target: str, sun_el: float, sun_az: float, spot_lla) -> None:
    spot = [float(v) for v in spot_lla]
    rec = {
        "motor_position": {"axis_1_motor_position": int(counts[0]), "axis_2_motor_position": int(counts[1])},
        "target_name": target,
        "sun_elevation": float(sun_el),
        "sun_azimuth": float(sun_az),
        "focal_spot": {"HeliOS": spot, "UTIS": spot},
    }
    path.write_text(json.dumps(rec, indent=2))
