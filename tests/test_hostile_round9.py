"""Hostile-input round 9: calibration-target names get the rule of heliostat ids
(:func:`heliojax._limits.target_name_problem`) in the tower file's reader and in
``--target``/``--targets`` (a target named ``=HYPERLINK(...)`` went raw into plan.csv, a
formula to a spreadsheet; blank, multi-line and 100 kB names loaded); the CLI's instants
are checked against the library's span (``aim --time 1900-...`` ended in a traceback);
``plan`` warns of a window before the fit's records."""

from __future__ import annotations

import argparse
import csv
import json
import logging
import shutil
from pathlib import Path

import pytest
from helpers import run_cli

import heliojax as hj
from heliojax._limits import EARLIEST_UNIX_S, LATEST_UNIX_S, target_name_problem
from heliojax.cli._common import target_name
from heliojax.paint import TowerFile, read_tower, write_paint_directory, write_tower

TOWER = "WRI1030197-tower-measurements.json"
LOWER = "solar_tower_juelich_lower"
FORMULA = '=HYPERLINK("http://evil","x")'
BAD_NAMES = [FORMULA, "+1+cmd", "-2+3", "@SUM(A1)", "\tX", "", " ", "lower\ntower", "T" * 100_000, " lower "]
REAL_NAMES = ["solar_tower_juelich_upper", LOWER, "multi_focus_tower", "receiver"]


@pytest.mark.parametrize("name", BAD_NAMES, ids=lambda n: repr(n)[:20])
def test_a_bad_target_name_is_refused_by_the_rule_and_by_the_options(name):
    assert target_name_problem(name) is not None
    with pytest.raises(argparse.ArgumentTypeError, match="is not a target name"):
        target_name(name)


def test_the_real_target_names_pass_and_a_formula_is_named_as_one():
    for name in REAL_NAMES:
        assert target_name_problem(name) is None and target_name(name) == name
    assert "spreadsheet formula" in (target_name_problem(FORMULA) or "")  # not its comma


def _tower_doc() -> dict:
    return json.loads((hj.default_data_dir() / TOWER).read_text())


def test_the_tower_reader_skips_a_target_of_a_bad_name_alone_and_says_so(tmp_path, caplog):
    doc = _tower_doc()
    for name in BAD_NAMES:
        doc[name] = doc[LOWER]
    doc["=junk"] = 5  # skipped unread: its malformed entry spoils nothing
    path = tmp_path / TOWER
    path.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING, logger="heliojax"):
        tower = read_tower(path)
    assert set(tower.targets) == set(REAL_NAMES)
    assert set(tower.skipped) == {*BAD_NAMES, "=junk"}
    warned = [r.getMessage() for r in caplog.records if "skipped target" in r.getMessage()]
    assert len(warned) == len(BAD_NAMES) + 1
    assert all(str(path) in m and "not a target name" in m for m in warned)
    assert any(FORMULA in m for m in warned)
    assert max(len(m) for m in warned) < 500  # the 100 kB name is shortened
    # the real tower files read as before
    for real in (hj.default_data_dir() / TOWER, Path("/work/shared/data/paint") / TOWER):
        if real.exists():
            assert set(REAL_NAMES) <= set(read_tower(real).targets) and not read_tower(real).skipped


def test_a_tower_of_bad_target_names_only_names_them(tmp_path):
    doc = {"power_plant_properties": _tower_doc()["power_plant_properties"], FORMULA: _tower_doc()[LOWER]}
    path = tmp_path / TOWER
    path.write_text(json.dumps(doc))
    with pytest.raises(hj.DataError, match="no planar calibration target.*skipped by name.*HYPERLINK"):
        read_tower(path)


def test_the_writers_refuse_a_target_the_reader_would_skip(tmp_path):
    tower = read_tower(hj.default_data_dir() / TOWER)
    bad = TowerFile(tower.plant_id, tower.origin_lla, {**tower.targets, FORMULA: tower.targets[LOWER]})
    with pytest.raises(hj.DataError, match="not a target name"):
        write_paint_directory(tmp_path / "out", bad, [], [])
    assert not (tmp_path / "out").exists()
    with pytest.raises(hj.DataError, match="not a target name"):
        write_tower(tmp_path / TOWER, bad)
    assert not (tmp_path / TOWER).exists()


def _renamed_target_copy(tmp_path: Path, new: str) -> Path:
    """The embedded data with target ``solar_tower_juelich_lower`` renamed ``new`` in the
    tower file and in every record that names it."""
    data = tmp_path / "paint"
    shutil.copytree(hj.default_data_dir(), data)
    doc = _tower_doc()
    (data / TOWER).write_text(json.dumps({(new if k == LOWER else k): v for k, v in doc.items()}))
    for f in data.glob("*/Calibration/*.json"):
        record = json.loads(f.read_text())
        if record["target_name"] == LOWER:
            record["target_name"] = new
            f.write_text(json.dumps(record))
    return data


def test_records_on_a_skipped_target_are_skipped_saying_why_and_the_rest_load(tmp_path):
    fleet = hj.load_paint_directory(_renamed_target_copy(tmp_path, FORMULA))
    assert FORMULA not in fleet.target_names and fleet.report.heliostats_loaded == 5
    reasons = [e.reason for e in fleet.report.skipped]
    assert reasons and all("the tower file's target of that name was skipped" in r for r in reasons)
    assert "spreadsheet formula" in reasons[0] and fleet.report.records_loaded > 0
    assert any("not a target name" in n for n in fleet.report.notes)
    with pytest.raises(hj.DataError, match="not a target name"):
        hj.load_paint_directory(tmp_path / "paint", strict=True)


def _plan_argv(fitted_h5, tmp_path, *more) -> list[str]:
    out = str(tmp_path / "plan.csv")
    quick = ["--budget", "1", "--step-minutes", "120", "--envelope-day-step", "60", "--model-discrepancy", "none"]
    return ["plan", str(fitted_h5), *quick, "--out", out, "--cache-dir", "none", *more]


def test_plan_writes_no_target_the_tower_reader_skipped(fitted_h5, tmp_path, capsys):
    """The formula's target first, a copy of the lower one: as good a candidate, it was
    chosen (plan.csv's target column held the formula)."""
    doc = _tower_doc()
    doc = {"power_plant_properties": doc["power_plant_properties"], FORMULA: doc[LOWER], LOWER: doc[LOWER]}
    doc["receiver"] = _tower_doc()["receiver"]
    tower = tmp_path / TOWER
    tower.write_text(json.dumps(doc))
    rc, _, err = run_cli(_plan_argv(fitted_h5, tmp_path, "--tower", str(tower), "--date", "2024-06-21"), capsys)
    assert rc == 0, err
    assert f"skipped target '{FORMULA}'" in err
    with open(tmp_path / "plan.csv", newline="") as f:
        targets = {row["target"] for row in csv.DictReader(f)}
    assert targets == {LOWER}, targets


@pytest.mark.parametrize(
    ("command", "option"),
    [
        ("aim", ["--target", FORMULA]),
        ("plan", ["--target", "@SUM(A1)"]),
        ("plan", ["--targets", "multi_focus_tower", "+1+cmd"]),
    ],
)
def test_a_formula_as_a_target_option_is_refused_by_name(command, option, tmp_path, capsys):
    rc, _, err = run_cli([command, str(tmp_path / "r.h5"), *option], capsys)
    assert rc == 2 and f"argument {option[0]}" in err and "spreadsheet formula" in err, err


def test_a_config_target_of_a_bad_name_is_refused_by_its_key(tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text('[plan]\ntargets = ["multi_focus_tower", "=1+1"]\n')
    rc, _, err = run_cli(["plan", str(tmp_path / "r.h5"), "--config", str(config)], capsys)
    assert rc == 2 and "targets" in err and "is not a target name" in err, err


@pytest.mark.parametrize(
    ("command", "option"),
    [
        ("aim", ["--time", "1900-06-21T12:00"]),
        ("aim", ["--date", "1900-06-21"]),
        ("aim", ["--date", "2200-12-31"]),
        ("aim", ["--date", "2200-01-01"]),
        ("aim", ["--time", "2200-01-01T00:00:01"]),
        ("aim", ["--time", "2199-12-31T23:00-05:00"]),  # 2200 in UTC
        ("aim", ["--start", "1969-12-31T12:00", "--end", "1970-01-01T12:00"]),
        ("aim", ["--start", "2023-06-21T12:00", "--end", "2200-06-21T12:00"]),
        ("plan", ["--date", "1900-06-21"]),
        ("plan", ["--date", "2200-12-31"]),
        ("plan", ["--start", "1969-12-31T12:00", "--end", "1970-01-01T12:00"]),
    ],
)
def test_an_instant_outside_the_librarys_span_is_refused_by_its_option(command, option, fitted_h5, capsys):
    """Was exit 1 with a traceback of instant_seconds (aim) or a silent plan of 1900."""
    rc, _, err = run_cli([command, str(fitted_h5), *option, "--cache-dir", "none"], capsys)
    bad = option[0] if option[0] != "--start" or option[1].startswith("1969") else "--end"
    assert rc == 2 and f"argument {bad}" in err and "1970-01-01T00:00Z" in err and "Traceback" not in err, err


def test_an_instant_of_a_config_outside_the_span_is_refused_by_its_key(fitted_h5, tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text("[aim]\ntime = 1900-06-21T12:00:00Z\n")
    rc, _, err = run_cli(["aim", str(fitted_h5), "--config", str(config), "--cache-dir", "none"], capsys)
    assert rc == 2 and "[aim] time" in err and "2200-01-01T00:00Z" in err and "Traceback" not in err, err


def test_the_cli_span_is_the_librarys():
    from heliojax.cli._aim import _utc

    assert _utc("1970-01-01T00:00Z").timestamp() == EARLIEST_UNIX_S
    assert _utc("2199-12-31T23:59:59Z").timestamp() == LATEST_UNIX_S - 1
    from heliojax._aim import instant_seconds  # the library takes the same ends

    assert instant_seconds([EARLIEST_UNIX_S, LATEST_UNIX_S - 1]).shape == (2,)
    with pytest.raises(ValueError):
        instant_seconds([LATEST_UNIX_S])
    with pytest.raises(argparse.ArgumentTypeError):
        _utc("2200-01-01T00:00Z")


def test_plan_warns_of_candidate_instants_before_the_fit(fitted_h5, tmp_path, capsys):
    """``plan --date 1990-06-21`` planned measurements 30 years before the fit's records
    without a word (aim flags such instants ``before_fit``)."""
    rc, _, err = run_cli(_plan_argv(fitted_h5, tmp_path, "--date", "1990-06-21", "--quiet"), capsys)
    assert rc == 0, err
    assert "--date: candidate instants 1990-06-21" in err and "before the first fitted record" in err, err
    assert "--paint-dir with --before" in err
    assert "further after the last fitted record" not in err, err
    rc, _, err = run_cli(_plan_argv(fitted_h5, tmp_path, "--date", "2024-12-21", "--quiet"), capsys)
    assert rc == 0 and "before the first fitted record" not in err, err
    assert "further after the last fitted record" not in err, err  # within the records' span after them
    # long after the fit (new-user trial, 2026-12-08: `plan` of today after a fit of 2022-2024
    # said nothing, where aim flags such instants long_after_fit): a warning naming the fits' ends
    rc, _, err = run_cli(_plan_argv(fitted_h5, tmp_path, "--date", "2031-06-21", "--quiet"), capsys)
    assert rc == 0 and "--date: candidate instants 2031-06-21" in err, err
    assert "further after the last fitted record of" in err and "may have drifted since" in err, err
