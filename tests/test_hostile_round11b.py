"""Hostile-input round 11b, the findings of round 11 left open: results.h5's record ids,
weights, flags, ``param_units`` and its ``robust`` / ``split`` attributes get the
writer's types and ranges (a float record id let plan take fitted records for new
candidates); ``fleet_subset`` and ``fleet_from_arrays`` refuse a heliostat twice; a
single heliostat id is one id, not its characters; ``PointingErrorLaw.from_dict`` names
what it expects; the loader shows a huge motor count compactly and names a
``Calibration`` that is a file; ``plan --envelope-year`` takes the library's years;
``verify_download`` reads nothing outside its folder; a download that replaces a file
keeps that file's mode."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import forged_results, run_cli
from test_stac import build_catalogue

import heliojax as hj
from heliojax.paint import JOURNAL_NAME, _stac as stac, fetch_catalog, verify_download


@pytest.fixture(scope="module")
def embedded() -> hj.Fleet:
    return hj.load_paint_directory()


def _replace(f, name: str, data) -> None:
    del f[name]
    f.create_dataset(name, data=data)


def _record_id_float(f):
    _replace(f, "record_id", f["record_id"][()].astype(float) + 0.5)


def _record_id_twice(f):
    rid = f["record_id"][()]
    rid[0, 1] = rid[0, 0]
    f["record_id"][...] = rid


def _record_id_negative(f):
    rid = f["record_id"][()]
    rid[0, 0] = -5
    f["record_id"][...] = rid


def _weight(value):
    def edit(f):
        w = f["weight"][()]
        w[0, 0] = value
        f["weight"][...] = w

    return edit


def _outlier_not_boolean(f):
    flags = f["outlier"][()].astype(np.int8)
    flags[0, 0] = 2
    _replace(f, "outlier", flags)


def _units_short(f):
    f.attrs["param_units"] = json.dumps(json.loads(f.attrs["param_units"])[:-1])


def _attr(name, value):
    def edit(f):
        f.attrs[name] = value

    return edit


@pytest.mark.parametrize(
    ("edit", "field", "said"),
    [
        (_record_id_float, "record_id", "not integers"),
        (_record_id_twice, "record_id", "listed twice"),
        (_record_id_negative, "record_id", "-5 is not a record id"),
        (_weight(np.nan), "weight", "nan is not a record weight"),
        (_weight(-0.5), "weight", "-0.5 is not a record weight"),
        (_outlier_not_boolean, "outlier", "not booleans"),
        (_units_short, "param_units", "7 units for the 8 param_names"),
        (_attr("robust", "no"), "robust", "not a boolean"),
        (_attr("split", 3), "split", "not the name of a split"),
    ],
    ids=[
        "rid-float",
        "rid-twice",
        "rid-negative",
        "weight-nan",
        "weight-negative",
        "outlier-2",
        "units",
        "robust",
        "split",
    ],
)
def test_results_record_fields_and_attributes_get_the_writers_types(fitted_h5, tmp_path, edit, field, said):
    """Each forgery (row checksums recomputed) was read; a float record id went through
    plan's records_among as int64, so a fitted record was taken for a new candidate."""
    results = forged_results(fitted_h5, tmp_path, edit)
    with pytest.raises(hj.DataError, match=said) as e:
        hj.load_results(results)
    assert e.value.field == field and e.value.file == str(results)


def test_results_padding_record_ids_still_load(fitted_h5):
    """-1 marks padding (the writer's and the PAINT fleet's): not a negative record id."""
    loaded = hj.load_results(fitted_h5)
    rid = loaded.records["record_id"]
    assert (rid == -1).any() and (loaded.records["split"][rid == -1] == 0).all()
    assert loaded.records["weight"].dtype == float and loaded.attrs["split"] == "time"


def test_fleet_subset_and_fleet_from_arrays_refuse_a_heliostat_twice(embedded, unchecked):
    """``fleet_subset(fleet, [0, 0])`` gave two copies of one heliostat (fitted and counted
    twice); ``fleet_from_arrays(ids=['A', 'A', ...])`` a fleet whose index() finds one."""
    fl = embedded
    for indices, said in (
        ([0, 0], r"heliostat 0 \('BE36'\) twice \(0 and 0\)"),
        ([1, -4], r"1 and -4"),
        (["BE36", 0], "twice"),
    ):
        with pytest.raises(ValueError, match=said):
            hj.fleet_subset(fl, indices)
    assert hj.fleet_subset(fl, [1, 0]).ids == (fl.ids[1], fl.ids[0])
    ids = ["A", "B", "A", "C", "D"]
    with pytest.raises(ValueError, match="ids: heliostat id 'A' is listed twice"):
        hj.fleet_from_arrays(fl.geometry, fl.counts, fl.context, fl.focal_spot, fl.mask, ids=ids)
    with pytest.raises(ValueError, match="ids: 2 heliostat ids for the 5"):
        hj.fleet_from_arrays(fl.geometry, fl.counts, fl.context, fl.focal_spot, fl.mask, ids=["A", "B"])


def test_a_single_heliostat_id_is_one_id_not_its_characters(tmp_path, unchecked):
    """``heliostats="BF56"`` asked for heliostats B, F, 5 and 6 (none there: an error, or
    with a folder named 'B' a wrong fleet)."""
    fleet = hj.load_paint_directory(heliostats="BF56")
    assert fleet.ids == ("BF56",)
    with pytest.raises(TypeError, match="heliostats"):
        hj.load_paint_directory(heliostats=56)  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match="heliostats: 56 .* is not a heliostat id"):
        hj.load_paint_directory(heliostats=["BF56", 56])  # pyright: ignore[reportArgumentType]
    data = hj.default_data_dir()
    csv_fleet = hj.paint.load_weather_csv_fleet(
        data / "calibration-with-weather.csv", data / "WRI1030197-tower-measurements.json", heliostats="BF56"
    )
    assert set(csv_fleet.ids) <= {"BF56"}
    root_json, _ = build_catalogue(tmp_path / "stac")
    report = fetch_catalog(root_json, tmp_path / "out", heliostats="BE36", include_tower=False)
    assert report is not None and (tmp_path / "out" / "BE36" / "Properties").is_dir()


def test_pointing_error_law_from_dict_names_what_it_expects(unchecked):
    """A list raised AttributeError ('list' object has no attribute 'get'); a misspelt key
    was read as the Gaussian's value; a string value gave float()'s message."""
    with pytest.raises(TypeError, match="from_dict: data: expected a mapping .* got list"):
        hj.PointingErrorLaw.from_dict([1, 2])  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match=r"unknown keys \['tail_dofs'\]"):
        hj.PointingErrorLaw.from_dict({"tail_dofs": 4.0})
    with pytest.raises(TypeError, match=r"data\['outlier_scale'\]: expected a number"):
        hj.PointingErrorLaw.from_dict({"outlier_scale": "3"})
    law = hj.PointingErrorLaw(tail_dof=4.0, outlier_fraction=0.1, outlier_scale=5.0)
    assert hj.PointingErrorLaw.from_dict(law.to_dict()) == law
    assert hj.PointingErrorLaw.from_dict(None) == hj.PointingErrorLaw()


def test_loader_shows_a_huge_count_compactly_and_names_a_calibration_file(tmp_path):
    """A count of 1e300 filled the report with its 301 digits; a file named
    ``<H>/Calibration`` was reported only as 'no valid calibration record'."""
    data = tmp_path / "paint"
    shutil.copytree(hj.default_data_dir(), data)
    record = sorted((data / "BE36" / "Calibration").glob("*.json"))[0]
    doc = json.loads(record.read_text())
    doc["motor_position"]["axis_1_motor_position"] = 1e300
    record.write_text(json.dumps(doc))
    shutil.rmtree(data / "BF56" / "Calibration")
    (data / "BF56" / "Calibration").write_text("not a folder")
    report = hj.load_paint_directory(data).report
    (count,) = [e for e in report.skipped if e.file == str(record)]
    assert "count 1e+300 outside" in count.reason and len(count.reason) < 200, count.reason
    (folder,) = [e for e in report.skipped if e.file == str(data / "BF56" / "Calibration")]
    assert "not a folder" in folder.reason
    with pytest.raises(hj.DataError, match="not a folder") as e:
        hj.load_paint_directory(data, heliostats=["BF56"], strict=True)
    assert e.value.file == str(data / "BF56" / "Calibration")


@pytest.mark.parametrize("year", ["1969", "1900", "2200"])
def test_plan_envelope_year_is_the_librarys_span(tmp_path, capsys, year):
    """1900 to 2200 were accepted: instants before 1970 or of 2200, which the library
    refuses everywhere else."""
    argv = ["plan", str(tmp_path / "missing.h5"), "--envelope-year", year, "--out", str(tmp_path / "p.csv")]
    rc, _, err = run_cli(argv, capsys)
    assert rc == 2 and "--envelope-year" in err and "1970" in err and "2199" in err, err
    rc, _, err = run_cli([*argv[:3], "2199", *argv[4:]], capsys)  # the year accepted: the missing file named
    assert rc == 2 and "--envelope-year" not in err and "missing.h5" in err, err
    with pytest.raises(ValueError, match="year must be in 1970 to 2199"):
        hj.operating_envelope(np.array([50.9, 6.4, 87.0]), year=int(year), day_step=73)


def test_verify_download_reads_nothing_outside_its_folder(tmp_path, monkeypatch):
    """Absolute and ``..`` journal paths, and a folder linked out, were read and hashed
    (a forged entry matching a file elsewhere was verified as all well)."""
    out = tmp_path / "out"
    (out / "BE36").mkdir(parents=True)
    inside = b'{"ok": true}'
    (out / "BE36" / "x.json").write_bytes(inside)
    secret = tmp_path / "elsewhere" / "secret.json"
    secret.parent.mkdir()
    secret.write_bytes(b'{"secret": 1}')
    (out / "linked").symlink_to(secret.parent)

    def entry(path, data):
        return json.dumps({"path": path, "href": "x", "size": len(data), "sha256": hashlib.sha256(data).hexdigest()})

    lines = [
        entry("BE36/x.json", inside),
        entry(str(secret), secret.read_bytes()),
        entry("../elsewhere/secret.json", secret.read_bytes()),
        entry("linked/secret.json", secret.read_bytes()),
    ]
    (out / JOURNAL_NAME).write_text("\n".join(lines) + "\n")
    read = []
    hash_file = stac._hash_file
    monkeypatch.setattr(stac, "_hash_file", lambda p, algos: read.append(Path(p)) or hash_file(p, algos))
    problems = verify_download(out)
    assert len(problems) == 3, problems
    assert any(str(secret) in p and "absolute path" in p for p in problems), problems
    assert any("../elsewhere" in p and "'..'" in p for p in problems), problems
    assert any("linked/secret.json" in p and "symbolic link" in p for p in problems), problems
    assert read == [out / "BE36" / "x.json"]


def test_a_replaced_download_keeps_the_files_mode_and_new_ones_get_todays_umask(tmp_path):
    """A file downloaded again (changed since, or --no-resume) got the mode of the umask
    read at import, not its own; a new file that umask, not the one of the fetch."""
    root_json, _ = build_catalogue(tmp_path / "stac")
    out = tmp_path / "out"
    fetch_catalog(root_json, out, heliostats=["BE36"], include_tower=False)
    record = sorted((out / "BE36" / "Calibration").glob("*.json"))[0]
    record.chmod(0o600)
    record.write_bytes(record.read_bytes() + b" ")  # changed: downloaded again on resume
    fetch_catalog(root_json, out, heliostats=["BE36"], include_tower=False)
    assert record.stat().st_mode & 0o777 == 0o600
    assert verify_download(out) == []
    mask = os.umask(0o077)
    try:
        fetch_catalog(root_json, tmp_path / "private", heliostats=["BE36"], include_tower=False)
    finally:
        os.umask(mask)
    properties = tmp_path / "private" / "BE36" / "Properties" / "BE36-heliostat-properties.json"
    assert properties.stat().st_mode & 0o777 == 0o600
