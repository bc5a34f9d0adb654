"""One rule for heliostat ids (:func:`heliojax._io.heliostat_id_problem`), shared by the
loader, the CLI's options, results.h5 and the CSV inputs: an id the loader takes can be
written and read back everywhere (hostile-input round 8: a folder ``' BL14 '`` was
calibrated and its results.h5 then refused by every later command; ``'BL,14'`` could not
be named in ``--exclude``; ``'=cmd|x'`` went raw into aim.csv, a formula to a
spreadsheet)."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import pytest

import heliojax as hj
from heliojax._io import heliostat_id_problem
from heliojax.cli._common import heliostat_id

RENAMED = "BL14"


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("AA39", None),
        ("AA 39", None),  # an inner space: another plant's naming
        ("Heliostat_7.b", None),
        (" BL14 ", "white space"),
        ("BL14 ", "white space"),
        ("BL,14", "comma"),
        ("=cmd|x", "formula"),
        ("+1", "formula"),
        ("-x", "formula"),
        ("@sum", "formula"),
        ("a/b", "path"),
        ("..", "path"),
        ("", "blank"),
        ("   ", "blank"),
        ("BL\t14", "unprintable"),
        ("x" * 256, "longer"),
    ],
)
def test_the_id_rule(text, problem):
    got = heliostat_id_problem(text)
    assert got is None if problem is None else problem in got
    if problem is None:
        assert heliostat_id(text) == text
    else:
        with pytest.raises(argparse.ArgumentTypeError, match="is not a heliostat id"):
            heliostat_id(text)


def _renamed_copy(tmp_path: Path, new: str) -> Path:
    """The embedded data with heliostat BL14 renamed ``new`` (folder, properties file,
    calibration-timestamps.json)."""
    data = tmp_path / "paint"
    shutil.copytree(hj.default_data_dir(), data)
    props = data / RENAMED / "Properties"
    (props / f"{RENAMED}-heliostat-properties.json").rename(props / f"{new}-heliostat-properties.json")
    (data / RENAMED).rename(data / new)
    stamps = data / "calibration-timestamps.json"
    doc = json.loads(stamps.read_text())
    for v in doc.values():
        if v["heliostat_id"] == RENAMED:
            v["heliostat_id"] = new
    stamps.write_text(json.dumps(doc))
    return data


@pytest.mark.parametrize("new", [" BL14 ", "BL,14", "=cmd|x"])
def test_the_loader_skips_a_folder_whose_name_is_no_id_and_names_it(new, tmp_path):
    data = _renamed_copy(tmp_path, new)
    fleet = hj.load_paint_directory(data)
    assert new not in fleet.ids and len(fleet.ids) == 4
    assert fleet.report.heliostats_skipped == 1
    skipped = [s for s in fleet.report.skipped if "not a heliostat id" in s.reason]
    assert len(skipped) == 1 and Path(skipped[0].file).name == new


def test_a_folder_with_an_inner_space_loads_and_its_results_read_back(tmp_path):
    from heliojax.cli._main import main

    data = _renamed_copy(tmp_path, "BL 14")
    out = tmp_path / "out" / "results.h5"
    assert main(["calibrate", str(data), "--out", str(out), "--max-steps", "3", "--cache-dir", "none", "--quiet"]) == 0
    assert "BL 14" in hj.load_results(out).ids
