"""Hostile-input round 11: results.h5's target names get the tower reader's rule (a
forged ``=HYPERLINK(...)`` or a name listed twice was read) and its origin an altitude
near the Earth; the planning library's public functions name the argument of a value
they would have read wrongly (``day_step`` 0 taken as 1, a minimum elevation of 1e9
degrees wrapped through the sine, milliseconds taken for seconds, a NaN use time that
aged nothing); ``plan`` no longer learns a model discrepancy of 0 mrad from no record
at all (a tower file without the fit's targets); ``accept --paint`` reads a folder whose
name holds glob characters; ``verify_download`` of a mistyped folder no longer says all
is well; the background loader of kept programs no longer aborts a Python caller's
interpreter at exit."""

from __future__ import annotations

import json
import shutil
import threading

import jax.numpy as jnp
import jax.random as jr
import numpy as np
import pytest
from helpers import forged_results, run_cli

import heliojax as hj
from heliojax import _programs
from heliojax.acceptance import find_tower_file, positions_from_paint
from heliojax.paint import JOURNAL_NAME, verify_download

TOWER = "WRI1030197-tower-measurements.json"
FORMULA = '=HYPERLINK("http://evil","x")'
ORIGIN = np.array([50.91342112, 6.38782476, 87.0])


@pytest.mark.parametrize(
    ("first", "said"),
    [(FORMULA, "spreadsheet formula"), ("solar_tower_juelich_lower", "listed twice"), ("  ", "not a target name")],
    ids=["formula", "twice", "blank"],
)
def test_results_target_names_get_the_tower_readers_rule(fitted_h5, tmp_path, capsys, first, said):
    """A target name heliojax never writes (the tower reader skips it, the writers refuse
    it) was read from results.h5, and plan matched the tower's targets to it."""
    import h5py

    def edit(f):
        names = [x.decode() for x in f["target_names"][()]]
        del f["target_names"]
        f.create_dataset("target_names", data=[first, *names[1:]], dtype=h5py.string_dtype())

    results = forged_results(fitted_h5, tmp_path, edit)
    with pytest.raises(hj.DataError, match=said) as e:
        hj.load_results(results)
    assert e.value.field == "target_names" and e.value.file == str(results)
    out = tmp_path / "aim.csv"
    rc, _, err = run_cli(["aim", str(results), "--time", "2023-06-21T12:00", "--out", str(out)], capsys)
    assert rc == 2 and "target_names" in err and "results.h5" in err and "Traceback" not in err, err
    assert not out.exists()


def test_results_origin_far_above_the_earth_is_named_not_blamed_on_the_tower(fitted_h5, tmp_path, capsys):
    """An origin altitude of 1e7 m was read; aim then called the embedded tower file one
    of another plant."""

    def edit(f):
        f.attrs["origin_lla"] = np.array([*f.attrs["origin_lla"][:2], 1e7])

    results = forged_results(fitted_h5, tmp_path, edit)
    with pytest.raises(hj.DataError, match="not near the Earth's surface") as e:
        hj.load_results(results)
    assert e.value.field == "origin_lla"
    rc, _, err = run_cli(["aim", str(results), "--time", "2023-06-21T12:00", "--out", str(tmp_path / "a.csv")], capsys)
    assert rc == 2 and "origin_lla" in err and "another plant" not in err, err


@pytest.mark.parametrize(
    ("options", "name"),
    [
        ({"day_step": 0}, "day_step"),  # was taken as 1
        ({"day_step": -5}, "day_step"),
        ({"day_step": 2.9}, "day_step"),  # was taken as 2
        ({"hour_step": 0.0}, "hour_step"),  # ZeroDivisionError
        ({"hour_step": -1.0}, "hour_step"),  # an empty envelope
        ({"hour_step": float("nan")}, "hour_step"),
        ({"min_elevation_deg": float("nan")}, "min_elevation_deg"),  # an empty envelope
        ({"min_elevation_deg": 1e9}, "min_elevation_deg"),
        ({"year": 2023.5}, "year"),
    ],
)
def test_operating_envelope_names_an_argument_out_of_range(unchecked, options, name):
    with pytest.raises(ValueError, match=name):
        hj.operating_envelope(ORIGIN, **{"day_step": 73, **options})
    with pytest.raises(ValueError, match="origin_lla"):
        hj.operating_envelope(np.array([np.nan, 6.0, 87.0]), day_step=73)  # was an empty envelope
    assert hj.operating_envelope(ORIGIN, day_step=73)[0].shape[0] > 0


def _two_heliostats():
    geometry = hj.synthetic_geometry(jr.PRNGKey(0), 2)
    return hj.random_stone_models(jr.PRNGKey(1), 2), geometry


@pytest.mark.parametrize(
    ("change", "said"),
    [
        ({"min_elevation_deg": 1e9}, "min_elevation_deg"),  # every candidate was valid
        ({"min_elevation_deg": float("nan")}, "min_elevation_deg"),  # none was
        ({"unix_time": "ms"}, "unix_time .*milliseconds"),
        ({"unix_time": "short"}, "unix_time has shape"),
        ({"target_index": np.array([-5])}, "target_index"),
        ({"centres": np.full((1, 3), np.nan)}, "target_centres must be finite"),  # none was valid
        ({"centres": np.array([0.0, -0.5, 40.0])}, "target_centres must be"),
    ],
    ids=["elevation-1e9", "elevation-nan", "milliseconds", "times-short", "index-5", "centre-nan", "centre-1d"],
)
def test_candidates_at_targets_names_an_argument_it_would_misread(unchecked, change, said):
    models, geometry = _two_heliostats()
    unix = 1.7e9 + 3600.0 * np.arange(4)
    sun = hj.solar_position(jnp.asarray(unix), *ORIGIN).direction_enu()
    centres = change.pop("centres", np.array([[0.0, -0.5, 40.0]]))
    change["unix_time"] = {"ms": unix * 1000.0, "short": unix[:2]}.get(change.get("unix_time", ""), unix)
    with pytest.raises(ValueError, match=said):
        hj.candidates_at_targets(models, geometry, sun, jnp.asarray(centres), **change)


def test_aged_noise_names_times_that_are_not_seconds_and_a_negative_noise(unchecked):
    """A NaN or infinite use time aged nothing, milliseconds aged a candidate by decades,
    and a negative noise was squared away, all silently."""
    day = 86400.0
    times = 1.7e9 + np.array([[0.0, 10 * day, np.nan]])
    valid = np.ones((1, 3), bool)
    for use in (np.nan, np.inf, 1.7e12):
        with pytest.raises(ValueError, match="use_unix_time"):
            hj.aged_noise_mrad(0.5, 0.01, times, valid, use_unix_time=use)
    with pytest.raises(ValueError, match="candidate_unix_time"):
        hj.aged_noise_mrad(0.5, 0.01, times * 1000.0, valid)
    for noise in (-1.0, np.nan):
        with pytest.raises(ValueError, match="noise_mrad"):
            hj.aged_noise_mrad(noise, 0.01, times, valid)
    with pytest.raises(ValueError, match=r"\(H, K\)"):
        hj.aged_noise_mrad(0.5, 0.01, times[0], valid[0])
    aged = hj.aged_noise_mrad(0.5, 0.01, times, valid, use_unix_time=times[0, 1])  # NaN candidate: unknown, kept
    np.testing.assert_allclose(aged[0] ** 2, [0.25 + 0.1, 0.25, 0.25], rtol=1e-12)


def test_plan_learns_no_discrepancy_from_no_record(fitted_h5, tmp_path, capsys):
    """A tower file without the fit's targets gave every record a NaN centre: plan
    'learnt' a discrepancy of 0.000 mrad (and 0.000 noise) from no record and planned as
    if the model were exact (median 26 instead of 62 mrad), with exit status 0."""
    doc = json.loads((hj.default_data_dir() / TOWER).read_text())
    renamed = {(k if k in ("power_plant_properties", "receiver") else f"{k}_2"): v for k, v in doc.items()}
    tower = tmp_path / TOWER
    tower.write_text(json.dumps(renamed))
    out = tmp_path / "plan.csv"
    quick = ["--budget", "1", "--step-minutes", "120", "--envelope-day-step", "73", "--cache-dir", "none"]
    argv = ["plan", str(fitted_h5), "--date", "2024-06-21", "--tower", str(tower), "--out", str(out), *quick]
    rc, _, err = run_cli(argv, capsys)
    assert rc == 2 and "nothing to learn the model discrepancy from" in err, err
    assert "--model-discrepancy none" in err and f"--tower {tower}" in err and "Traceback" not in err, err
    assert not out.exists()
    results = hj.load_results(fitted_h5)
    with pytest.raises(hj.DataError, match="no centre for 'solar_tower_juelich_upper'"):
        hj.discrepancy_from_results(results, np.full((len(results.target_names), 3), np.nan))
    with pytest.raises(ValueError, match="a row for each of the 3 target_names"):  # records of target 2 were dropped
        hj.discrepancy_from_results(results, np.zeros((2, 3)))


def test_accept_reads_a_paint_folder_named_with_glob_characters(tmp_path):
    """``accept --paint 'run[1]'`` said the folder had no tower file (its name was read
    as a glob pattern); calibrate read the same folder."""
    data = tmp_path / "run[1]"
    shutil.copytree(hj.default_data_dir(), data)
    assert find_tower_file(data) == data / TOWER
    ids, positions = positions_from_paint(data)
    ids0, positions0 = positions_from_paint(hj.default_data_dir())
    assert ids == ids0 and len(ids) == 5
    np.testing.assert_array_equal(positions, positions0)


def test_verify_download_of_a_folder_fetch_never_wrote_is_an_error(tmp_path):
    """A mistyped folder, a file, a folder without the journal: each was verified as one
    where all is well (an empty list of problems)."""
    (tmp_path / "file").write_text("x")
    (tmp_path / "empty").mkdir()
    for path, field in ((tmp_path / "missing", None), (tmp_path / "file", None), (tmp_path / "empty", JOURNAL_NAME)):
        with pytest.raises(hj.DataError) as e:
            verify_download(path)
        assert e.value.file == str(path) and e.value.field == field
    (tmp_path / "empty" / JOURNAL_NAME).write_text("")
    assert verify_download(tmp_path / "empty") == []  # fetched nothing: nothing wrong


def test_the_program_preloader_is_waited_for_at_exit_and_stops_there(tmp_path, monkeypatch):
    """The preloader was a daemon thread: a Python caller's interpreter that exited while
    it was inside XLA's deserializer (two commands through ``main`` in one process) was
    aborted ("terminate called ... FATAL: exception not rethrown", status 134). It is
    waited for, and reads no further executable once the main thread has ended."""
    monkeypatch.setattr(_programs, "_program_dir", lambda: tmp_path)
    names = [f"{k:064x}{_programs.EXECUTABLE_SUFFIX}" for k in range(3)]
    for name in names:
        (tmp_path / name).write_bytes(b"")
    (tmp_path / f"round11{_programs.RECENT_SUFFIX}").write_text("\n".join(names) + "\n")
    started, release, read = threading.Event(), threading.Event(), []

    def slow_read(path):
        read.append(path)
        started.set()
        release.wait(10.0)

    monkeypatch.setattr(_programs, "_read_executable", slow_read)
    before = set(threading.enumerate())
    _programs.preload("round11")
    (loader,) = [t for t in threading.enumerate() if t not in before and t.name == _programs._PRELOAD_THREAD]
    try:
        assert started.wait(10.0)
        assert not loader.daemon
        ended = threading.Thread(target=lambda: None)  # never started: not alive, as the main thread at exit
        monkeypatch.setattr(threading, "main_thread", lambda: ended)
    finally:
        release.set()
        loader.join(10.0)
    assert not loader.is_alive() and len(read) == 1
    assert all(f.done() and f.result() is None for f in _programs._PRELOADED.values())
    _programs._PRELOADED.clear()
