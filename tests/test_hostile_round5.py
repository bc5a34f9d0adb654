"""Hostile input, round 5: impossible field layouts (positions in km), the source of
the heliostat positions of ``accept``, contract tower files that are not files, mixed
aim-point frames and Python API arguments of the wrong kind."""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import forged_results, run_cli, write_file

import heliojax as hj
from heliojax.acceptance._io import check_spacing

CONTRACT = """
[parameters.tracking_mrad]
mean = 2.0
std = 0.2
rel_error = 0.04

[yield]
step_minutes = 720
"""
"""A contract of one parameter and a coarse year (the tests are about the inputs)."""

_IDS = ("BE36", "BF56", "BG23", "BH20", "BL14")


_run, _file = run_cli, write_file


def _accept(tmp: Path, results: str, contract: str = CONTRACT) -> list[str]:
    contract_path = _file(tmp, "contract.toml", contract)
    return ["accept", "--results", results, "--contract", contract_path, "--report", str(tmp / "acc.json")]


# ---- A: physically impossible layouts


def test_accept_refuses_a_field_whose_positions_are_in_km(tmp_path, capsys):
    """Heliostats 30-60 m from the tower written in km (0.03-0.06) stand centimetres
    apart; the field was accepted with a plausible efficiency."""
    rows = "".join(f"H{k},{0.01 * k:.3f},{0.03 + 0.005 * k:.3f},1.{k}\n" for k in range(4))
    field = _file(tmp_path, "field.csv", "heliostat_id,east_m,north_m,tracking_mrad\n" + rows)
    rc, _, err = _run(_accept(tmp_path, field), capsys)
    assert rc == 2, err
    assert "field.csv" in err and "'H0' (line 2)" in err and "'H1' (line 3)" in err, err
    assert "m apart" in err and "km instead of m" in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) <= 2 and not (tmp_path / "acc.json").exists()


def test_spacing_check_names_the_closest_pair_of_a_large_field():
    """A 100 x 100 grid of heliostats 5 m apart passes; moving one to 0.3 m from its
    neighbour is refused naming both and their distance (a k-d tree, no pair loop)."""
    e, n = np.meshgrid(np.arange(100) * 5.0, 30.0 + np.arange(100) * 5.0)
    pos = np.column_stack([e.ravel(), n.ravel(), np.zeros(e.size)])
    ids = tuple(f"S{k:05d}" for k in range(len(pos)))
    check_spacing("grid.csv", ids, pos)
    pos[5001, :2] = pos[5000, :2] + [0.3, 0.0]
    with pytest.raises(hj.DataError, match=r"'S05000' and 'S05001' are 0\.3 m apart") as info:
        check_spacing("grid.csv", ids, pos)
    assert info.value.file == "grid.csv"


def test_accept_warns_of_a_heliostat_at_the_tower_foot(tmp_path, capsys):
    """A heliostat 0.3 m from the receiver's tower (in km, or a wrong origin) was used
    without a word; the warning names the file, the heliostat and its distance."""
    text = "heliostat_id,east_m,north_m,tracking_mrad\nNEAR,0.0,-0.2,1.9\nFAR,0,60,2.1\nFAR2,10,60,2.0\n"
    rc, _, err = _run(_accept(tmp_path, _file(tmp_path, "field.csv", text)), capsys)
    assert rc == 0, err
    assert "field.csv" in err and "'NEAR'" in err and "m from the tower" in err and "km instead of m" in err, err


# ---- B: which positions a summary.json is judged with


def _summary_and_positions(tmp: Path) -> tuple[str, str]:
    summary = {
        "heliostats": {
            h: {"status": "converged", "test_rms_mrad": 1.5 + 0.1 * k, "n_test": 3} for k, h in enumerate(_IDS)
        }
    }
    rows = "".join(f"{h},{10.0 * k},{50.0 + 5 * k}\n" for k, h in enumerate(_IDS))
    return (
        _file(tmp, "summary.json", json.dumps(summary)),
        _file(tmp, "pos.csv", "heliostat_id,east_m,north_m\n" + rows),
    )


def test_accept_says_that_positions_beat_paint_and_records_the_source(tmp_path, capsys):
    """--positions and --paint together: --positions was used silently and the report
    did not say which positions it judged."""
    summary, pos = _summary_and_positions(tmp_path)
    argv = [*_accept(tmp_path, summary), "--positions", pos, "--paint", str(hj.default_data_dir())]
    rc, _, err = _run(argv, capsys)
    assert rc == 0, err
    assert f"--positions {pos} given" in err and "--paint" in err and "not used" in err, err
    inputs = json.loads((tmp_path / "acc.json").read_text())["inputs"]
    assert inputs["positions"] == pos and inputs["positions_from"].startswith("--positions"), inputs
    assert "not used" in inputs["positions_from"]


def test_accept_report_names_the_positions_of_a_field_csv(tmp_path, capsys):
    field = _file(tmp_path, "field.csv", "heliostat_id,east_m,north_m,tracking_mrad\nA,0,60,1.9\nB,5,60,2.1\n")
    rc, _, err = _run(_accept(tmp_path, field), capsys)
    assert rc == 0, err
    inputs = json.loads((tmp_path / "acc.json").read_text())["inputs"]
    assert inputs["positions"] == field and inputs["positions_from"].startswith("--results"), inputs


# ---- C: a contract tower file that is not a file


@pytest.mark.parametrize(
    ("where", "said"), [("dir", "is a directory"), ("/dev/zero", "exists and is not a regular file")]
)
def test_contract_tower_file_that_is_no_regular_file_is_not_called_missing(where, said, tmp_path, capsys):
    tower = str(tmp_path) if where == "dir" else where
    field = _file(tmp_path, "field.csv", "heliostat_id,east_m,north_m,tracking_mrad\nA,0,60,1.9\n")
    rc, _, err = _run(_accept(tmp_path, field, CONTRACT + f'tower_file = "{tower}"\n'), capsys)
    assert rc == 2 and "contract.toml" in err and "tower_file" in err and said in err, err
    assert "not found" not in err


# ---- D and E: aim points


@pytest.mark.parametrize(
    ("header", "cells", "column", "said"),
    [
        ("east_m,north_m,up_m,lat_deg", "0,0,120,50", "lat_deg", "a WGS84 column beside the ENU columns"),
        ("lat_deg,lon_deg,alt_m,up_m", "50.9,6.38,200,120", "up_m", "an ENU column beside the WGS84 columns"),
        ("east_m,north_m,up_m,note", "0,0,120,x", "note", "unknown column"),
    ],
)
def test_aim_csv_of_mixed_frames_or_unknown_columns_is_refused(
    header, cells, column, said, fitted_h5, tmp_path, capsys
):
    """lat_deg beside east_m,north_m,up_m was dropped without a word (the ENU columns used)."""
    text = f"heliostat_id,{header}\n" + "".join(f"{h},{cells}\n" for h in _IDS)
    path = _file(tmp_path, "m.csv", text)
    out = tmp_path / "o.csv"
    argv = ["aim", str(fitted_h5), "--time", "2023-06-21T10:00:00Z", "--aim-csv", path, "--out", str(out), "--quiet"]
    rc, _, err = _run(argv, capsys)
    assert rc == 2 and "m.csv" in err and f"'{column}'" in err and said.split(" beside")[0] in err, err
    assert not out.exists()


_SUN = jnp.array([[0.0, -0.5, np.sqrt(0.75)]])
_AIM = jnp.array([0.0, 0.0, 55.0])


def _unchecked(function):
    """``function`` without the test run's jaxtyping/beartype wrapper: the checks under
    test are the function's own, which a user (no runtime type checker) meets."""
    return getattr(function, "__wrapped__", function)


@pytest.mark.parametrize("results", [None, "results.h5", Path("results.h5")])
def test_aim_results_names_a_results_argument_that_is_no_calibration(results):
    with pytest.raises(TypeError, match=r"results: expected a CalibrationResults \(heliojax\.load_results\(path\)\)"):
        _unchecked(hj.aim_results)(results, _SUN, _AIM)


def test_aim_results_names_bad_sun_and_aim_points(fitted_h5):
    results = hj.load_results(fitted_h5)
    with pytest.raises(TypeError, match=r"^sun: expected .* got str 'south'"):
        _unchecked(hj.aim_results)(results, "south", _AIM)
    for bad, k in ((jnp.full(3, jnp.nan), 3), (jnp.array([0.0, jnp.inf, 55.0]), 1)):
        with pytest.raises(ValueError, match=rf"^aim_points: {k} of 3 coordinate\(s\) are not finite"):
            hj.aim_results(results, _SUN, bad)


@pytest.mark.parametrize("path", [5, ["base"]])
def test_load_paint_directory_names_a_path_of_the_wrong_type(path):
    with pytest.raises(TypeError, match=r"^path: expected a directory path .* got (int|list)"):
        _unchecked(hj.load_paint_directory)(path)


@pytest.mark.parametrize(
    "dataset, value, message",
    [
        ("residual_mrad", 1e200, "no pointing error exceeds"),
        ("sun_elevation_deg", 200.0, "outside -90..90 deg"),
        ("sun_azimuth_deg", np.nan, "not finite for a record of the fit's split"),
    ],
)
def test_forged_record_values_outside_their_range_are_refused(fitted_h5, tmp_path, dataset, value, message):
    """Values edited in results.h5 with the row checksum recomputed (a forgery, or a
    tool that rewrites the file) passed every check; a residual of 1e200 mrad then
    moved the other heliostats' plans (a hostile-input trial, round 5). A value no
    pointing error or sun position can take is refused, naming the dataset."""
    import shutil

    import h5py

    from heliojax._results import CHECKSUM_DATASET, _row_checksums

    results = tmp_path / "results.h5"
    shutil.copy(fitted_h5, results)
    with h5py.File(results, "r+") as f:
        data = f[dataset][...]
        fitted = np.argwhere(f["split"][...] != 0)[0]
        data[tuple(fitted)] = value
        f[dataset][...] = data
        f[CHECKSUM_DATASET][...] = _row_checksums(f, len(f["heliostat_ids"]))
    with pytest.raises(hj.DataError, match=message) as e:
        hj.load_results(results)
    assert e.value.field == dataset and e.value.file == str(results)


def test_a_parameter_forged_within_its_bounds_is_found_by_the_residuals(fitted_h5, tmp_path, caplog):
    """A parameter edited within every plausibility bound, the row checksum recomputed,
    passed (an axis tilt of pi aimed with, ok=1: hostile-input trial, round 5). The file
    now holds its records' inputs, and the parameters must reproduce its residuals: the
    forged heliostat is flagged (not aimed with), the others keep their fits."""
    clean = hj.load_results(fitted_h5)
    assert clean.flags == {}
    h = next(i for i, s in enumerate(clean.status) if s in ("converged", "max_steps"))
    column = list(clean.view.names).index(clean.view.free_names[0])

    def edit(f):
        params = f["params"][...]
        params[h, column] += 1e-6  # a micro-radian: far inside any bound
        f["params"][...] = params

    with caplog.at_level("WARNING", logger="heliojax"):
        forged = hj.load_results(forged_results(fitted_h5, tmp_path, edit))
    assert list(forged.flags) == [clean.ids[h]]
    assert "do not reproduce its residuals" in forged.flags[clean.ids[h]]
    assert clean.ids[h] in caplog.text


def test_residuals_are_reproduced_without_x64(fitted_h5):
    """The check computes in float64 whatever the caller's ``jax_enable_x64``: in a
    plain user's configuration (float32; in float32 the residuals differ by up to
    1e-3 mrad) it flags nothing."""
    import jax

    with jax.enable_x64(False):
        assert not jax.config.jax_enable_x64
        assert hj.load_results(fitted_h5).flags == {}


def test_a_heliostat_with_records_after_the_file_was_written_is_flagged(fitted_h5, tmp_path):
    """Record times moved to 2191 (within 1970-2200) lowered that heliostat's predicted
    uncertainty without a word (round 5). A record cannot be later than its file: that
    heliostat is flagged (not aimed with), the others keep their fits (round 6: refusing
    the whole file lost every heliostat for one whose records a loader had dated in the
    future, which calibrate keeps with a warning)."""
    clean = hj.load_results(fitted_h5)
    h = next(i for i, s in enumerate(clean.status) if s in ("converged", "max_steps"))

    def edit(f):
        t = f["unix_time"][...]
        t[h][np.isfinite(t[h])] = 7.0e9  # 2191
        f["unix_time"][...] = t

    forged = hj.load_results(forged_results(fitted_h5, tmp_path, edit))
    assert list(forged.flags) == [clean.ids[h]]
    assert "later than the file was written" in forged.flags[clean.ids[h]]


@pytest.mark.parametrize("how", ["deleted", "a dataset"])
def test_a_file_without_its_record_inputs_is_refused(fitted_h5, tmp_path, how):
    """Deleting ``record_inputs`` (and recomputing the checksum) switched the residual
    check off and an edited parameter was aimed with (round 6). A file that says when it
    was written has the group (both are written since 2026-12-07): without it, or with
    something else in its place, the file is refused."""

    def edit(f):
        del f["record_inputs"]
        if how == "a dataset":
            f["record_inputs"] = np.zeros(3)

    with pytest.raises(hj.DataError, match="missing group|not a group") as e:
        hj.load_results(forged_results(fitted_h5, tmp_path, edit))
    assert e.value.field == "record_inputs"


def test_a_file_written_after_now_is_warned_of(fitted_h5, tmp_path, caplog):
    def edit(f):
        f.attrs["written_unix_time"] = 7.0e9

    with caplog.at_level("WARNING", logger="heliojax"):
        hj.load_results(forged_results(fitted_h5, tmp_path, edit))
    assert "later than this machine's clock" in caplog.text


def test_results_of_a_newer_heliojax_are_read_with_a_warning(fitted_h5, tmp_path, caplog):
    """A results.h5 that says a newer heliojax wrote it was read without a word."""
    import shutil

    import h5py

    results = tmp_path / "results.h5"
    shutil.copy(fitted_h5, results)
    with caplog.at_level("WARNING", logger="heliojax"):
        hj.load_results(results)
    assert "newer than this heliojax" not in caplog.text
    with h5py.File(results, "r+") as f:
        f.attrs["heliojax_version"] = "99.0"
    with caplog.at_level("WARNING", logger="heliojax"):
        hj.load_results(results)
    assert "written by heliojax 99.0, newer than this heliojax" in caplog.text


def test_discover_leaves_out_the_heliostats_it_is_told_to(capsys, tmp_path):
    """The report's warning about a garbage heliostat says to run without it:
    ``--exclude`` does so; an unknown id or excluding every heliostat is a usage error
    naming the ids (before anything is fitted)."""
    from heliojax.cli._discover import excluded_ids
    from heliojax.discovery._select import _without_heliostats

    fleet = hj.load_paint_directory(hj.default_data_dir())
    assert excluded_ids(" BL14, BE36,BL14 ") == ("BL14", "BE36") and excluded_ids(None) == ()
    kept = _without_heliostats(fleet, ("BL14", "BE36"))
    assert kept.ids == tuple(i for i in fleet.ids if i not in ("BL14", "BE36"))
    np.testing.assert_array_equal(np.asarray(kept.counts), np.asarray(fleet.counts)[[fleet.index(i) for i in kept.ids]])
    from helpers import unchecked_config

    with pytest.raises(ValueError, match="exclude must be a sequence of heliostat ids"):
        unchecked_config(exclude="BL14")
    assert unchecked_config(exclude=["BL14"]).exclude == ("BL14",)
    report = str(tmp_path / "r.json")
    for exclude, message in (
        ("BL14,XX99", "XX99 not among the 5 heliostats loaded"),
        (",".join(fleet.ids), "no heliostat"),
        (" , ", "no heliostat id given"),
    ):
        rc, _, err = _run(["discover", "--exclude", exclude, "--report", report, "--quiet"], capsys)
        assert rc == 2 and message in err, err
    assert not Path(report).exists()
