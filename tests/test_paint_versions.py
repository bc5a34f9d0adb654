"""Files of other PAINT versions and PAINT's own download layout.

heliojax is run on PAINT downloads it has never seen. PAINT's format changed over its
versions (checked in PAINT's history: the kinematics key renamed in commit e644ef5,
the reference pose labelled ``[0, 0, 1]`` from f1fc4bf to 6cad13e, the joint
translation keys renamed in 3bd4c37, ``type_axis`` lower-cased in 2a7068d), PAINT
writes values it lacks as JSON ``NaN``, and PAINT's own STAC client writes no
``calibration-timestamps.json`` (the record times are in its metadata CSV, or
nowhere). Each variant of the embedded data must load as the same fleet as the
original, with the difference named in the load report.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

import heliojax as hj
from heliojax._errors import DataError
from heliojax._splits import split_fleet
from heliojax._workflow import _split_times
from heliojax.paint import read_deflectometry_facets

HELIOSTAT = "BL14"


def _properties(data: Path) -> Path:
    return data / HELIOSTAT / "Properties" / f"{HELIOSTAT}-heliostat-properties.json"


def _edit_properties(data: Path, edit) -> None:
    path = _properties(data)
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))  # json.dumps writes NaN as PAINT's json.dump does


def _older_kinematics_key(doc: dict) -> None:
    doc["kinematic_properties"] = doc.pop("kinematics_properties")


def _orientation_up(doc: dict) -> None:
    doc["initial_orientation"] = [0.0, 0.0, 1.0]


def _orientation_not_unit(doc: dict) -> None:
    doc["initial_orientation"] = [0.0, -1000.0, 0.0]


def _upper_case_actuator_type(doc: dict) -> None:
    for a in doc["kinematics_properties"]["actuators"]:
        a["type_axis"] = a["type_axis"].upper()


def _optional_key_nan(doc: dict) -> None:
    doc["kinematics_properties"]["actuators"][0]["movement_speed"] = float("nan")


def _older_joint_keys(doc: dict) -> None:
    kin = doc["kinematics_properties"]
    for c in "enu":
        kin[f"first_joint_translation_{c}"] = kin.pop(f"joint_translation_{c}_1")
        kin[f"second_joint_translation_{c}"] = kin.pop(f"joint_translation_{c}_2")


PROPERTY_VARIANTS = [
    ("kinematic_properties (PAINT before 3.0)", _older_kinematics_key, "kinematic_properties"),
    ("initial_orientation [0, 0, 1] (PAINT 2024-12 to 2025-11)", _orientation_up, "initial_orientation"),
    ("initial_orientation [0, -1000, 0] (south, not a unit vector)", _orientation_not_unit, "initial_orientation"),
    ("type_axis LINEAR (PAINT before 2024-12-06)", _upper_case_actuator_type, None),
    ("movement_speed NaN (an optional key PAINT lacked)", _optional_key_nan, "actuators[0].movement_speed"),
    ("first_joint_translation_e (PAINT before 2024-12-05)", _older_joint_keys, "first_joint_translation_e"),
]


@pytest.fixture(scope="module")
def original():
    return hj.load_paint_directory(hj.default_data_dir())


def _copy(tmp_path: Path) -> Path:
    data = tmp_path / "paint"
    shutil.copytree(hj.default_data_dir(), data)
    return data


def _same_fleet(a, b) -> None:
    assert a.ids == b.ids
    for x, y in zip(
        [a.counts, a.mask, a.record_id, *a.geometry.__dict__.values()],
        [b.counts, b.mask, b.record_id, *b.geometry.__dict__.values()],
        strict=True,
    ):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(np.asarray(a.context.unix_time), np.asarray(b.context.unix_time))


@pytest.mark.parametrize(("edit", "field"), [c[1:] for c in PROPERTY_VARIANTS], ids=[c[0] for c in PROPERTY_VARIANTS])
def test_properties_of_older_paint_versions_load_as_the_same_heliostat(edit, field, original, tmp_path):
    """Each of these dropped the heliostat and its records ("missing", "is not south",
    "unsupported actuator type 'LINEAR'", "not finite")."""
    data = _copy(tmp_path)
    _edit_properties(data, edit)
    fleet = hj.load_paint_directory(data)
    assert fleet.report.heliostats_skipped == 0 and fleet.report.records_loaded == original.report.records_loaded
    _same_fleet(fleet, original)
    flagged = [e for e in fleet.report.flags if Path(e.file).name == _properties(data).name]
    if field is None:
        assert not flagged
    else:
        assert any(e.field is not None and e.field.endswith(field) for e in flagged), flagged


def test_an_unknown_orientation_and_actuator_type_are_still_refused(tmp_path):
    data = _copy(tmp_path)
    _edit_properties(data, lambda d: d.update(initial_orientation=[1.0, 0.0, 0.0]))
    assert HELIOSTAT not in hj.load_paint_directory(data).ids
    data = _copy(tmp_path / "b")
    _edit_properties(data, lambda d: d["kinematics_properties"]["actuators"][1].update(type_axis="rotary"))
    fleet = hj.load_paint_directory(data)
    assert HELIOSTAT not in fleet.ids
    assert any("rotary" in e.reason for e in fleet.report.skipped)


@pytest.mark.parametrize(("bad", "good"), [("UTIS", "HeliOS"), ("HeliOS", "UTIS")])
def test_a_centroid_written_as_nan_is_read_as_missing(bad, good, original, tmp_path):
    """PAINT writes a centroid it could not compute as NaN; the record was skipped."""
    data = _copy(tmp_path)
    path = sorted((data / HELIOSTAT / "Calibration").iterdir())[0]
    doc = json.loads(path.read_text())
    doc["focal_spot"][bad] = [float("nan")] * 3
    path.write_text(json.dumps(doc))
    fleet = hj.load_paint_directory(data, centroid="helios" if good == "HeliOS" else "utis")
    assert fleet.report.records_loaded == original.report.records_loaded
    assert any(e.field == f"focal_spot.{bad}" and "NaN" in e.reason for e in fleet.report.flags)
    # both centroids NaN: the record is skipped, naming the field
    doc["focal_spot"][good] = [float("nan")] * 3
    path.write_text(json.dumps(doc))
    fleet = hj.load_paint_directory(data)
    assert fleet.report.records_loaded == original.report.records_loaded - 1
    assert any(e.field == "focal_spot" and "no usable centroid" in e.reason for e in fleet.report.skipped)


def _metadata_csv(data: Path) -> None:
    """PAINT's ``get_heliostat_metadata`` output for the download's records (columns and
    pandas' date-time format as PAINT writes them), in place of the timestamps file."""
    stamps = json.loads((data / "calibration-timestamps.json").read_text())
    (data / "calibration-timestamps.json").unlink()
    (data / "metadata").mkdir()
    with open(data / "metadata" / "calibration_metadata_all_heliostats.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["Id", "HeliostatId", "Azimuth", "Elevation", "lower_left_latitude", "DateTime"])
        for rid, entry in stamps.items():
            when = entry["datetime"].replace("T", " ").replace("Z", "+00:00")
            w.writerow([rid, entry["heliostat_id"], -10.0, 30.0, 50.91, when])


def test_record_times_from_paints_metadata_csv(original, tmp_path):
    data = _copy(tmp_path)
    _metadata_csv(data)
    fleet = hj.load_paint_directory(data)
    _same_fleet(fleet, original)
    assert any("calibration_metadata_all_heliostats.csv" in n for n in fleet.report.notes)
    # beside the timestamps file, a record the two disagree on is named, the file's time kept
    data = _copy(tmp_path / "b")
    _metadata_csv(data)
    shutil.copy(hj.default_data_dir() / "calibration-timestamps.json", data)
    path = next((data / "metadata").iterdir())
    rows = path.read_text().splitlines()
    rid = rows[1].split(",")[0]
    rows[1] = rows[1].rsplit(",", 1)[0] + ",2030-01-01 12:00:00+00:00"
    path.write_text("\n".join(rows) + "\n")
    fleet = hj.load_paint_directory(data)
    _same_fleet(fleet, original)
    assert any(e.field == f"record {rid}" and "2030-01-01" in e.reason for e in fleet.report.flags)


def test_without_any_record_time_the_time_split_orders_by_record_id(original, tmp_path):
    """PAINT numbers records in measurement order (the 1,706 timestamped ids of the
    shared download are strictly chronological), so without times the time split is the
    one the times give. Before, calibrate's default split exited with an error."""
    data = _copy(tmp_path)
    (data / "calibration-timestamps.json").unlink()
    fleet = hj.load_paint_directory(data)
    assert not np.isfinite(np.asarray(fleet.context.unix_time)[np.asarray(fleet.mask)]).any()

    def masks(f):
        az = np.zeros(f.mask.shape)
        times = _split_times(f, "time")
        s = split_fleet("time", az, az, times, list(f.ids), valid=np.asarray(f.mask), train_fraction=0.7)
        return np.asarray(s.train_mask), np.asarray(s.test_mask)

    for got, want in zip(masks(fleet), masks(original), strict=True):
        np.testing.assert_array_equal(got, want)
        assert want.any()


def test_paints_flat_dataset_layout_is_named(tmp_path):
    data = tmp_path / "flat"
    data.mkdir()
    src = hj.default_data_dir()
    shutil.copy(next(src.glob("*-tower-measurements.json")), data)
    for f in (src / HELIOSTAT).rglob("*.json"):
        shutil.copy(f, data)
    with pytest.raises(DataError, match="one folder"):
        hj.load_paint_directory(data)


def test_records_before_the_renovation_are_flagged(tmp_path):
    data = _copy(tmp_path)
    _edit_properties(data, lambda d: d.update(renovation="2023-01-02/2099-01-29"))
    fleet = hj.load_paint_directory(data)
    assert any(e.field == "renovation" and "before the retrofit" in e.reason for e in fleet.report.flags)
    assert HELIOSTAT in fleet.ids


def test_a_deflectometry_normal_of_zero_length_is_named(tmp_path):
    path = tmp_path / "d.h5"
    with h5py.File(path, "w") as f:
        g = f.create_group("facet1")
        g.create_dataset("surface_points", data=np.zeros((3, 3)))
        g.create_dataset("surface_normals", data=np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(DataError, match="row 1 is a zero vector"):
        read_deflectometry_facets(path)


def test_times_of_paint_before_3_are_named_whole_hours_early(tmp_path):
    """PAINT before 3.0 converted its times as if they were Europe/Berlin local time, so
    they are 1 h (winter) or 2 h (summer) early. The suns then disagree with most times;
    the records are kept and the flag names the whole-hour shift."""
    import datetime as dt
    from zoneinfo import ZoneInfo

    data = _copy(tmp_path)
    path = data / "calibration-timestamps.json"
    stamps = json.loads(path.read_text())
    berlin = ZoneInfo("Europe/Berlin")
    for entry in stamps.values():
        utc = dt.datetime.fromisoformat(entry["datetime"].replace("Z", "+00:00"))
        early = utc - utc.astimezone(berlin).utcoffset()
        entry["datetime"] = early.strftime("%Y-%m-%dT%H:%M:%SZ")
    path.write_text(json.dumps(stamps))
    fleet = hj.load_paint_directory(data)
    assert fleet.report.records_loaded == 392
    (flag,) = [e for e in fleet.report.flags if "whole hours" in e.reason]
    assert "+1 h" in flag.reason or "+2 h" in flag.reason


def test_a_download_without_times_is_calibrated_and_aimed(tmp_path, capsys):
    """The whole path of a download without record times: calibrate (time split by
    record id, no drift), then aim and plan with its results.h5, which refused it
    before ("unix_time: not finite for a record of the fit's split")."""
    from heliojax.cli._main import main

    data = _copy(tmp_path)
    (data / "calibration-timestamps.json").unlink()
    results = tmp_path / "out" / "results.h5"
    assert main(["calibrate", str(data), "--out", str(results), "--quiet"]) == 0
    assert "5/5 converged" in capsys.readouterr().out
    loaded = hj.load_results(results)
    assert loaded.drift_mrad2_per_day == 0.0
    aim_csv = tmp_path / "out" / "aim.csv"
    assert main(["aim", str(results), "--time", "2024-06-01T10:00:00Z", "--out", str(aim_csv), "--quiet"]) == 0
    with aim_csv.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 5 and all(np.isfinite(float(r["pointing_std_mrad"])) for r in rows)
