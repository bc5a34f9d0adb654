"""Hostile-input round 10, optics: ``reconstruct --paint`` skips a damaged record (a
blank or unreadable flux PNG, a truncated record JSON, no focal spot) with a warning and
lists it in reconstruction.json instead of stopping (F1); a record without flux images is
named as such, also by ``--held-out`` (F2); ``loss_first_last`` averages a window that
scales with the steps, the divergence check's (F9); ``trace --dni`` so small that the
flux underflows float32 says so instead of blaming the aim (F4); the ARTIST reader
refuses control points far from their facet or off its plane (F6)."""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
from conftest import SHARED_PAINT
from helpers import run_cli
from PIL import Image

import heliojax as hj
from heliojax._errors import DataError
from heliojax.cli._reconstruct import _loss_rose
from heliojax.optics import flux_records, flux_sample_records, loss_window
from heliojax.paint import read_artist_scenario

TOWER = "WRI1030197-tower-measurements.json"
SCENARIO = SHARED_PAINT.parent / "artist-scenarios" / "paint_four_heliostats_deflectometry.h5"
SMALL = ["--steps", "2", "--rays-per-point", "2", "--n-ctrl", "4", "--quiet"]


@pytest.fixture
def aa39(tmp_path, shared_paint):
    """A copy of AA39's three flux records (270398, 271633, 275564) and the tower file."""
    root = tmp_path / "paint"
    shutil.copytree(shared_paint / "flux-samples" / "AA39", root / "AA39")
    shutil.copy(shared_paint / TOWER, root / TOWER)
    return root


def _calibration(root):
    return root / "AA39" / "Calibration"


def _blank_png(path):
    Image.fromarray(np.zeros((256, 256), np.uint8)).save(path)


def _reconstruct(root, out, capsys, caplog, *extra):
    with caplog.at_level("WARNING"):
        rc, stdout, err = run_cli(
            ["reconstruct", "--paint", str(root), "--heliostat", "AA39", *SMALL, "--out", str(out), *extra], capsys
        )
    return rc, stdout, err + caplog.text


def test_reconstruct_skips_a_damaged_record_and_one_without_images(aa39, tmp_path, capsys, caplog):
    """F1 + F2 + F9: a blank flux PNG (270398) and a record whose PNGs are gone (275564)
    used to end the run with exit 2 (the first) or vanish without a word (the second);
    now both are named, listed as skipped, and 271633 is reconstructed. With 2 steps the
    first and last loss are those of step 1 and step 2, not one 10-step mean twice."""
    cal = _calibration(aa39)
    _blank_png(cal / "270398-flux.png")
    for png in cal.glob("275564-flux*.png"):
        png.unlink()
    rc, _, err = _reconstruct(aa39, tmp_path / "o", capsys, caplog)
    assert rc == 0, err
    assert "270398-flux.png" in err and "no flux spot" in err, err
    assert "275564" in err and "no flux image" in err, err
    report = json.loads((tmp_path / "o" / "reconstruction.json").read_text())
    assert [r["record"] for r in report["records"]] == [271633]
    skipped = {r["record"]: r["reason"] for r in report["skipped_records"]}
    assert set(skipped) == {270398, 275564}
    assert "no flux spot" in skipped[270398] and "no flux image" in skipped[275564]
    first, last = report["loss_first_last"]
    assert report["loss_window_steps"] == 1 and first != last


def test_reconstruct_exits_2_only_when_no_record_is_usable(aa39, tmp_path, capsys, caplog):
    cal = _calibration(aa39)
    for png in cal.glob("*-flux.png"):
        png.write_bytes(b"")
    rc, _, err = _reconstruct(aa39, tmp_path / "o", capsys, caplog)
    assert rc == 2 and "no usable flux record of AA39" in err, err
    assert not (tmp_path / "o").exists()


def test_held_out_names_why_its_record_cannot_be_scored(aa39, tmp_path, capsys, caplog):
    """F2: ``--held-out`` of a record without flux images said 'not records of AA39';
    of a damaged record it now names the damage."""
    cal = _calibration(aa39)
    for png in cal.glob("270398-flux*.png"):
        png.unlink()
    _blank_png(cal / "271633-flux.png")
    rc, _, err = _reconstruct(aa39, tmp_path / "o", capsys, caplog, "--held-out", "270398")
    assert rc == 2 and "record 270398 of AA39 has no flux image" in err and "not records" not in err, err
    rc, _, err = _reconstruct(aa39, tmp_path / "o", capsys, caplog, "--held-out", "271633")
    assert rc == 2 and "--held-out 271633: the record cannot be used" in err and "271633-flux.png" in err, err


def test_flux_records_skips_a_truncated_json_and_a_record_without_focal_spot(aa39, caplog):
    """F1 in the library: ``skip_bad=True`` leaves the records out with their reasons
    (without it, the first bad record raises, as before)."""
    cal = _calibration(aa39)
    truncated = cal / "270398-calibration-properties.json"
    truncated.write_text(truncated.read_text()[:100])
    no_spot = cal / "271633-calibration-properties.json"
    record = json.loads(no_spot.read_text())
    record.pop("focal_spot")
    no_spot.write_text(json.dumps(record))
    pairs = [p for p in flux_sample_records(aa39) if p[1].parent.parent.name == "AA39"]
    with pytest.raises(DataError, match="270398-calibration-properties.json"):
        flux_records(pairs, aa39 / TOWER, pixels=16)
    with caplog.at_level("WARNING"):
        records = flux_records(pairs, aa39 / TOWER, pixels=16, skip_bad=True)
    assert records.record_ids == (275564,)
    reasons = dict(records.skipped)
    assert set(reasons) == {"270398", "271633"}
    assert "malformed JSON" in reasons["270398"] and "focal_spot" in reasons["271633"]
    assert "270398-calibration-properties.json" in caplog.text and "271633" in caplog.text
    assert records.subset([0]).skipped == records.skipped


def test_loss_window_is_shared_by_the_report_and_the_divergence_check():
    """F9: one window, a fifth of the steps within 1..10, for both."""
    assert [loss_window(n) for n in (1, 2, 9, 10, 24, 25, 50, 1000)] == [1, 1, 1, 2, 4, 5, 10, 10]
    losses = [1.0] * 4 + [0.5] * 12 + [2.0] * 4  # 20 steps: window 4, the end above the start
    assert _loss_rose(losses) == (1.0, 2.0)


def test_trace_at_an_underflowing_dni_says_so(tmp_path, capsys, caplog):
    """F4: at ``--dni 1e-38`` the float32 flux is all zeros; the warning blamed the aim
    ('the spot is off the image'). It names the underflow and --dni now."""
    data = tmp_path / "paint"
    shutil.copytree(hj.default_data_dir(), data)
    argv = ["trace", str(data), "--heliostat", "BE36", "--sun-azimuth", "10", "--sun-elevation", "30"]
    argv += ["--pixels", "32", "--rays-per-point", "1", "--steps", "1", "--dni", "1e-38", "--quiet"]
    with caplog.at_level("WARNING"):
        rc, _, err = run_cli([*argv, "--out", str(tmp_path / "t")], capsys)
    text = err + caplog.text
    assert rc == 0, text
    assert "underflows" in text and "--dni 1e-38" in text and "off the image" not in text, text


def _damaged_scenario(tmp_path, change) -> str:
    if not SCENARIO.exists():
        pytest.skip(f"ARTIST scenario not found at {SCENARIO}")
    path = tmp_path / "damaged.h5"
    shutil.copy(SCENARIO, path)
    with h5py.File(path, "r+") as f:
        d = f["heliostats/AA39/surface/facets/facet_4/control_points"]
        cp = d[()]
        change(cp)
        d[...] = cp
    return str(path)


def test_artist_reader_refuses_a_control_point_far_from_its_facet(tmp_path):
    """F6: flipped bytes read as a control point 954 m away on a 1.6 m facet were
    accepted and scored; the dataset is named now."""

    def far(cp):
        cp[3, 5, 0] = 954.8

    damaged = _damaged_scenario(tmp_path, far)
    assert read_artist_scenario(SCENARIO).heliostats  # the real file passes
    with pytest.raises(DataError, match=r"facet_4/control_points.*from the facet's centre"):
        read_artist_scenario(damaged)


def test_artist_reader_refuses_a_control_point_off_the_facet_plane(tmp_path):
    def raised(cp):
        cp[10, 10, 2] += 0.5  # half a metre above a 1.6 m x 1.3 m facet

    with pytest.raises(DataError, match=r"facet_4/control_points.*off the facet's plane"):
        read_artist_scenario(_damaged_scenario(tmp_path, raised))
