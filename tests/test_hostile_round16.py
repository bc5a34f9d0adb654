"""Hostile-input round 16: the output paths of the CLI, a new user's process environment,
and the public acceptance and PAINT reading APIs as a Python user calls them.

Output paths: ``accept --report figs/field_map.png --figures figs`` wrote the report over
that figure (exit 0), and ``accept --results figs/field_map.png --figures figs`` (as
``reconstruct --scenario out/control_points.h5 --out out``) replaced its input by an
output: the files written inside an output folder were checked against the other outputs
of other commands only, never against the inputs. With no data folder given, an output
inside heliojax's embedded data (the input of such a run) was not checked at all:
``calibrate --report <embedded tower file>`` replaced the tower file by a summary.

Environment: an ASCII standard output (``PYTHONUTF8=0 LC_ALL=C``, a ``PYTHONIOENCODING``)
ended ``heliojax plan --help`` (the 'ü' of Jülich) in a UnicodeEncodeError traceback. With
an unwritable ``$HOME`` matplotlib printed two lines of warnings and left a
``/tmp/matplotlib-*`` folder behind on every run (its removal at exit is skipped by the
CLI's quick exit), and the compilation cache's warning named no folder.

PAINT API: an int given as a path was opened as a file descriptor (``read_tower(0)``
read standard input and closed it), None or a list failed inside ``os.stat``, an empty
path was the working directory (``load_paint_directory("")`` loaded it without a word);
``heliostat_properties_path`` / ``calibration_record_path`` took ``../x`` for an id (out
of the root) and record ids of 2.5 or -1 (names the reader refuses).

Acceptance API: ``find_tower_file(None)`` / ``positions_from_paint(None)`` searched the
working directory, and a missing folder or a file was "no tower file in the PAINT
directory"; ``FieldData`` took what the field CSV's reader refuses (a string of ids read
one per letter, integer ids, an infinite value taken as "not measured", a tracking error
of 1e5 mrad, a NaN position failing in SciPy's KD-tree, a negative value in the KDE's
logarithm, positions 1,000 km off); ``run_acceptance`` of a path, of None or of a NaN or
two-number plant failed as an AttributeError or ran, and with a ``sun`` of no samples it
failed level 2 on a year without sun; ``fit_kde`` took a negative or NaN bandwidth (NaN
densities) and ``cv_bandwidth_factor(n_grid=0)`` divided by zero;
``extrapolate_field`` read measured index -1 as the last heliostat, failed in NumPy on
one past the field and extrapolated from NaN "measurements", as ``select_sample`` did
with an ``exclude`` past the field; ``typical_year`` of a NaN latitude or a negative
step gave a year without sun and of a step of 0 divided by zero. ``outliers`` of a NaN
threshold flagged nothing, ``find_clusters`` took ``alpha=5`` and handed a length scale
of 0 to scikit-learn, and ``sample_size`` took a field of 2.5 heliostats;
``contract_values(n=-1)`` returned no values (of a NaN ``std`` NaN ones) and
``synthetic_field(0)`` failed in a NumPy concatenation.

Ill-typed values are given under the ``unchecked`` fixture.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli, write_file

import heliojax as hj
from heliojax import acceptance, paint
from heliojax._errors import DataError
from heliojax.cli._main import main

CONTRACT = "[parameters.tracking_mrad]\nmean = 2.0\nstd = 0.2\nrel_error = 0.04\n"
FIELD = "heliostat_id,east_m,north_m,tracking_mrad\nA1,0,50,1\nA2,6,50,2\n"


def _environment(tmp_path: Path, **env: str) -> dict[str, str]:
    """The test's environment for a CLI subprocess, with ``env`` and without the variables
    that would hide what a new user meets (a set matplotlib or cache folder)."""
    drop = ("MPLCONFIGDIR", "XDG_CACHE_HOME", "XDG_CONFIG_HOME", "HELIOJAX_CACHE_DIR", "PYTHONIOENCODING")
    environ = {k: v for k, v in os.environ.items() if k not in drop}
    return {**environ, "PYTHONPATH": str(Path(hj.__file__).parents[1]), **env}


def test_an_ascii_standard_output_escapes_what_it_cannot_encode(tmp_path):
    """``PYTHONUTF8=0 LC_ALL=C heliojax plan --help > help.txt``: the 'ü' of 'Jülich' was
    a UnicodeEncodeError traceback, exit 1; it is written escaped, as stderr writes it."""
    run = subprocess.run(
        [sys.executable, "-m", "heliojax.cli._main", "plan", "--help"],
        cwd=tmp_path,
        env=_environment(tmp_path, LC_ALL="C", LANG="C", PYTHONUTF8="0"),
        capture_output=True,
        timeout=600,
    )
    assert run.returncode == 0 and b"Traceback" not in run.stderr, run.stderr[-2000:]
    assert b"J\\xfclich" in run.stdout
    # the same in this process: an ASCII text stream as sys.stdout
    stream = io.TextIOWrapper(io.BytesIO(), encoding="ascii")
    saved = sys.stdout
    sys.stdout = stream
    try:
        with pytest.raises(SystemExit) as ended:
            main(["aim", "--help"])
    finally:
        sys.stdout = saved
    stream.flush()
    assert ended.value.code == 0 and b"J\\xfclich" in stream.buffer.getvalue()  # pyright: ignore[reportAttributeAccessIssue]


def test_a_new_users_environment_with_an_unwritable_home_leaves_nothing_behind(tmp_path):
    """``HOME`` a file (no folder can be made under it), a C locale, ``TERM=dumb``,
    ``NO_COLOR``, ``COLUMNS=20``, output piped to a file, a figure named with a space
    and an 'é': matplotlib printed two lines of warnings and left a
    ``matplotlib-*`` folder in ``$TMPDIR`` on every run; the compilation cache's warning
    named no folder."""
    home = Path(write_file(tmp_path, "home", "not a folder"))
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    env = _environment(
        tmp_path, HOME=str(home), TMPDIR=str(temporary), LC_ALL="C", LANG="C", TERM="dumb", NO_COLOR="1", COLUMNS="20"
    )
    run = subprocess.run(
        [sys.executable, "-m", "heliojax.cli._main", "inspect", "--plot", "fig \u00e9.png"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        encoding="utf-8",
        errors="replace",
        timeout=600,
    )
    assert run.returncode == 0 and "Traceback" not in run.stderr, run.stderr[-2000:]
    assert "atplotlib" not in run.stderr and "mkdir -p failed" not in run.stderr, run.stderr
    assert f"no compilation cache in {home}/.cache/heliojax/jax (Not a directory)" in run.stderr, run.stderr
    assert (tmp_path / "fig \u00e9.png").stat().st_size > 0
    assert list(temporary.iterdir()) == []  # the private matplotlib folder was removed


def test_a_report_named_like_a_figure_of_its_folder_is_refused(tmp_path, capsys, monkeypatch):
    """``accept --figures figs --report figs/field_map.png`` wrote the report over the
    field map (exit 0): the figures ``--figures`` receives are now checked like the
    other outputs."""
    monkeypatch.chdir(tmp_path)
    args = ["accept", "--results", write_file(tmp_path, "field.csv", FIELD)]
    args += ["--contract", write_file(tmp_path, "contract.toml", CONTRACT)]
    rc, _, err = run_cli([*args, "--figures", "figs", "--report", "figs/field_map.png"], capsys)
    assert rc == 2 and "--report names the same path" in err and "Traceback" not in err, err
    assert not (tmp_path / "figs").exists()


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (
            ["accept", "--results", "out/field_map.png", "--contract", "contract.toml", "--figures", "out"],
            "--results out/field_map.png: is out/field_map.png, a file --figures writes",
        ),
        (
            ["reconstruct", "--scenario", "out/control_points.h5", "--out", "out", "--steps", "1"],
            "--scenario out/control_points.h5: is out/control_points.h5, a file --out writes",
        ),
    ],
    ids=["accept-results", "reconstruct-scenario"],
)
def test_an_input_among_the_files_an_output_folder_receives_is_refused(argv, said, tmp_path, capsys, monkeypatch):
    """An input that is one of the files the command writes into its output folder was
    replaced by that output (accept's field CSV by a figure, exit 0)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").mkdir()
    write_file(tmp_path, "contract.toml", CONTRACT)
    write_file(tmp_path / "out", argv[2].split("/")[1], FIELD)
    rc, _, err = run_cli(argv, capsys)
    assert rc == 2 and said in err and "Traceback" not in err, err
    assert (tmp_path / argv[2]).read_text() == FIELD
    assert sorted(p.name for p in tmp_path.rglob("*")) == sorted(["out", "contract.toml", argv[2].split("/")[1]])


@pytest.mark.parametrize(
    "argv",
    [
        ["calibrate", "--report", "{data}/WRI1030197-tower-measurements.json"],
        ["inspect", "--plot", "{data}/p.png", "--cache-dir", "none"],
        ["aim", "r.h5", "--out", "{data}/aim.csv"],
    ],
    ids=["calibrate-report-onto-its-tower-file", "inspect-plot", "aim-out"],
)
def test_an_output_inside_the_embedded_data_is_refused(argv, tmp_path, capsys, monkeypatch):
    """Run without a data folder, a command reads the embedded data; an output there
    was not checked (no input path was given): the tower file was replaced by a
    summary. Here the embedded data is a stand-in folder."""
    data = tmp_path / "embedded"
    data.mkdir()
    tower = Path(write_file(data, "WRI1030197-tower-measurements.json", "{}"))
    monkeypatch.setattr(paint, "default_data_dir", lambda: data)
    monkeypatch.chdir(tmp_path)
    rc, _, err = run_cli([a.format(data=data) for a in argv], capsys)
    assert rc == 2 and "inside heliojax's embedded data" in err and "Traceback" not in err, err
    assert tower.read_text() == "{}" and sorted(p.name for p in data.iterdir()) == [tower.name]


READERS = [
    paint.read_tower,
    paint.read_timestamps,
    paint.read_weather_csv,
    paint.read_facets,
    paint.read_flux_png,
    paint.read_heliostat_properties,
    paint.read_calibration_record,
    acceptance.read_field_csv,
    acceptance.read_positions_csv,
    acceptance.read_summary,
    acceptance.load_contract,
    acceptance.load_receiver,
]


@pytest.mark.parametrize("reader", READERS, ids=[r.__name__ for r in READERS])
def test_a_path_that_is_no_path_or_empty_is_named(reader, unchecked):
    """An int was opened as a file descriptor (0: standard input, read and closed),
    None or a list failed inside ``os.stat`` or ``pathlib``, "" read the working
    directory or named no file."""
    for value in (987_654, None, ["a.json"]):
        with pytest.raises(TypeError, match=r"^path: expected a file or folder path \(str or os.PathLike\), got"):
            reader(value)
    with pytest.raises(ValueError, match=r"^path: empty path"):
        reader("")


def test_a_paint_folder_that_is_none_empty_missing_or_a_file_is_named(tmp_path, unchecked, monkeypatch):
    """``find_tower_file(None)`` and ``positions_from_paint(None)`` searched the working
    directory (a PAINT download there was read); a missing folder or a file was "no
    tower file in the PAINT directory"; ``load_paint_directory("")`` loaded the working
    directory."""
    monkeypatch.chdir(hj.default_data_dir())  # a PAINT folder: None had found its tower file
    for call in (acceptance.find_tower_file, acceptance.positions_from_paint):
        with pytest.raises(TypeError, match="^paint_dir: expected a file or folder path"):
            call(None)
        with pytest.raises(DataError, match=r"not a directory \(missing\)"):
            call(tmp_path / "missing")
        with pytest.raises(DataError, match=r"not a directory \(a file\)"):
            call(write_file(tmp_path, "a-file", "x"))
    with pytest.raises(ValueError, match="^path: empty path"):
        paint.load_paint_directory("")


def test_paint_path_builders_refuse_ids_that_leave_the_root_or_no_record(tmp_path, unchecked):
    """``heliostat_properties_path(root, "../x")`` named a file outside ``root``; record
    ids of 2.5, -1 or "5" named files the reader refuses (or that are not its); an int
    id failed as "unsupported operand type(s) for /"."""
    with pytest.raises(ValueError, match=r"^heliostat_id: '\.\./x' is not a heliostat id"):
        paint.heliostat_properties_path(tmp_path, "../x")
    with pytest.raises(TypeError, match="^heliostat_id: expected a heliostat id"):
        paint.heliostat_properties_path(tmp_path, 5)
    for record, kind in ((2.5, ValueError), (-1, ValueError), ("5", TypeError), (True, TypeError)):
        with pytest.raises(kind, match="^record_id: expected a whole number >= 0"):
            paint.calibration_record_path(tmp_path, "AA39", record)
    with pytest.raises(ValueError, match="^heliostat_id: 'A/B'"):
        paint.calibration_record_path(tmp_path, "A/B", 5)
    assert paint.calibration_record_path(tmp_path, "AA39", np.int64(7)).name == "7-calibration-properties.json"


def _field(**changes):
    """A field of 3 heliostats (of the field CSV's rules) with ``changes``."""
    kwargs = {
        "ids": ("A", "B", "C"),
        "positions": np.array([[0.0, 50.0, 0.0], [6.0, 50.0, 0.0], [12.0, 50.0, 0.0]]),
        "values": {"tracking_mrad": np.array([1.0, np.nan, 2.0])},
    }
    return acceptance.FieldData(**{**kwargs, **changes})


@pytest.mark.parametrize(
    ("changes", "kind", "said"),
    [
        ({"ids": "ABC"}, TypeError, "^ids: expected a tuple of heliostat ids"),
        ({"ids": (1, 2, 3)}, TypeError, "^ids: expected a tuple of heliostat ids"),
        ({"values": None}, TypeError, "^values: expected a dict"),
        ({"values": {"tracking_mrad": np.array([1.0, np.inf, 2.0])}}, ValueError, "heliostat 'B': inf is not finite"),
        ({"values": {"tracking_mrad": np.array([1.0, 1e5, 2.0])}}, ValueError, "'B': 100000.0 above 1000 mrad"),
        ({"values": {"tracking_mrad": np.array([-1.0, 1.0, 2.0])}}, ValueError, "'A': -1.0 outside the positive"),
        ({"values": {"reflectance": np.array([0.9, 1.2, 0.9])}}, ValueError, "'B': 1.2 outside the unit range"),
        ({"values": {"tracking_mrad": np.array(["1", "2", "3"])}}, TypeError, "expected numbers"),
        ({"positions": np.array([[0.0, 50, 0], [np.nan, 50, 0], [12, 50, 0]])}, ValueError, "positions: heliostat 'B'"),
        ({"positions": np.array([[0.0, 50, 0], [1e6, 50, 0], [12, 50, 0]])}, ValueError, "positions: heliostat 'B'"),
        ({"positions": np.array([[0.0, 50, 0], [6, 50, 5000], [12, 50, 0]])}, ValueError, "positions: heliostat 'B'"),
    ],
    ids=[
        "ids-a-string",
        "ids-ints",
        "values-none",
        "inf",
        "above-maximum",
        "negative",
        "reflectance-above-1",
        "strings",
        "nan-position",
        "1000-km",
        "5-km-up",
    ],
)
def test_field_data_keeps_the_field_csv_readers_rules(changes, kind, said, unchecked):
    with pytest.raises(kind, match=said):
        _field(**changes)


def test_run_acceptance_names_arguments_of_another_kind_and_a_sun_of_no_samples(unchecked):
    """A path for the field or the contract, None for the aperture failed as an
    AttributeError deep inside; a NaN or two-number plant ran (or blamed the contract's
    sun); a ``sun`` of no samples failed level 2 on a year without sun."""
    field, contract = _field(), acceptance.Contract({"tracking_mrad": acceptance.ParameterSpec(2.0, 0.2, 0.04)})
    receiver, plant = acceptance.juelich_receiver(), acceptance.JUELICH_COORDINATES
    for args, said in (
        (("field.csv", contract, receiver, plant), "field: expected a FieldData"),
        ((field, "contract.toml", receiver, plant), "contract: expected a Contract"),
        ((field, contract, None, plant), "aperture: expected a TargetPlane"),
    ):
        with pytest.raises(TypeError, match=f"^run_acceptance: {said}"):
            acceptance.run_acceptance(*args)
    for bad in ((float("nan"), 6.4, 90.0), (50.9, 6.4), (95.0, 6.4, 90.0), "Juelich"):
        with pytest.raises(ValueError, match="^run_acceptance: plant_lla: expected 3 finite numbers"):
            acceptance.run_acceptance(field, contract, receiver, bad)  # pyright: ignore[reportArgumentType]
    empty = acceptance.SunSeries(np.zeros(0), np.zeros(0, int), np.zeros((0, 3)), np.zeros(0), 1800.0)
    with pytest.raises(ValueError, match="^run_acceptance: sun: expected a SunSeries of at least one sample, got 0"):
        acceptance.run_acceptance(field, contract, receiver, plant, sun=empty)


def test_a_kde_bandwidth_that_is_no_factor_is_named(unchecked):
    """A negative or NaN bandwidth factor made a KDE of NaN densities; an unknown rule
    name reached SciPy; ``n_grid=0`` divided by zero."""
    values = np.array([1.0, 1.5, 2.0, 2.5])
    for bad in (-1.0, float("nan"), 0.0, np.inf, True, "scot"):
        with pytest.raises(ValueError, match="^bandwidth must be 'cv', 'scott', 'silverman' or a"):
            acceptance.fit_kde(values, bandwidth=bad)  # pyright: ignore[reportArgumentType]
    assert acceptance.fit_kde(values, bandwidth=0.5).bandwidth_factor == 0.5
    with pytest.raises(ValueError, match="^cv_bandwidth_factor: n_grid must be at least 1, got 0"):
        acceptance.cv_bandwidth_factor(values, n_grid=0)


def test_field_indices_outside_the_field_fractional_or_twice_are_named(unchecked):
    """``extrapolate_field`` read measured index -1 as the last heliostat (a silent
    wrong field), failed in NumPy on one past the field, extrapolated from a NaN
    "measurement" and from none; ``select_sample(exclude=[99])`` failed in NumPy."""
    xy = np.column_stack([np.arange(10.0) * 6.0, np.full(10, 50.0)])
    values = np.array([1.0, 1.5, 2.0])
    for measured, said in (
        ([-1, 2, 3], "measured: heliostat index -1 outside the field's \\[0, 9\\]"),
        ([1, 2, 10], "measured: heliostat index 10 outside"),
        ([1, 2, 2], "measured: heliostat index 2 given twice"),
        ([1.0, 2.5, 3.0], "measured: expected a 1-D array of heliostat indices"),
    ):
        with pytest.raises(ValueError, match=f"^{said}"):
            acceptance.extrapolate_field(xy, np.asarray(measured), values)
    with pytest.raises(ValueError, match="^values: not finite for heliostat index 2"):
        acceptance.extrapolate_field(xy, np.array([1, 2, 3]), np.array([1.0, np.nan, 2.0]))
    with pytest.raises(ValueError, match="^measured: no heliostat measured"):
        acceptance.extrapolate_field(xy, np.zeros(0, int), np.zeros(0))
    with pytest.raises(ValueError, match="^exclude: heliostat index 99 outside"):
        acceptance.select_sample(xy, 2, exclude=np.array([99]))
    assert acceptance.extrapolate_field(xy, np.array([1, 2, 3]), values).measured.sum() == 3


def test_a_typical_year_of_a_nan_plant_or_a_step_of_no_minutes_is_named(unchecked):
    """A NaN latitude and a negative step gave a year without sun (``run_acceptance``
    then blamed the contract's minimum elevation); a step of 0 divided by zero."""
    for kwargs, said in (
        ({"latitude_deg": float("nan")}, "latitude_deg must be a finite real number"),
        ({"altitude_m": float("inf")}, "altitude_m must be a finite real number"),
        ({"step_minutes": 0.0}, r"step_minutes must lie in \[1, 1440\] minutes, got 0.0"),
        ({"step_minutes": -30.0}, r"step_minutes must lie in \[1, 1440\]"),
        ({"step_minutes": float("nan")}, "step_minutes must be a finite real number"),
    ):
        with pytest.raises(ValueError, match=f"^typical_year: {said}"):
            acceptance.typical_year(**{"latitude_deg": 50.9, "longitude_deg": 6.4, **kwargs})


def test_cluster_and_sample_size_options_out_of_range_are_named(unchecked):
    """Left by the round at first, then fixed: ``outliers`` of a NaN threshold flagged
    nothing (of -1 everything) and a ``reference`` of another length failed inside NumPy;
    ``find_clusters`` took ``alpha=5`` (every cluster an anomaly) and passed a length
    scale of 0 or ``min_samples=0`` to scikit-learn; ``sample_size`` took a field of 2.5
    heliostats."""
    v = np.array([1.0, 1.1, 0.9, 1.0, 5.0])
    assert acceptance.outliers(v).tolist() == [False, False, False, False, True]
    for bad in (float("nan"), -1.0):
        with pytest.raises(ValueError, match="outliers: z_threshold must be a finite number >= 0"):
            acceptance.outliers(v, z_threshold=bad)
    with pytest.raises(ValueError, match=r"outliers: reference has shape \(3,\); expected \(5,\)"):
        acceptance.outliers(v, reference=np.ones(3, bool))
    xy = np.zeros((5, 2))
    for kw, said in (
        ({"alpha": 5.0}, "alpha must be a significance level"),
        ({"length_scale_m": 0.0}, "length_scale_m must be a finite length > 0"),
        ({"min_samples": 0}, "min_samples must be at least 1"),
    ):
        with pytest.raises(ValueError, match=f"find_clusters: {said}"):
            acceptance.find_clusters(xy, v, **{"length_scale_m": 10.0, **kw})
    with pytest.raises(ValueError, match="population must be a whole number"):
        acceptance.sample_size(2.0, 0.2, 0.04, population=2.5)
    assert acceptance.sample_size(2.0, 0.2, 0.04, population=1001) >= 1


def test_contract_values_and_synthetic_fields_of_no_heliostat_are_named(unchecked):
    """``contract_values(n=-1)`` returned no values, of a NaN ``std`` NaN values and of a
    misspelled ``support`` normal ones; ``synthetic_field(0)`` failed in a NumPy
    concatenation."""
    for kw, said in (
        ({"n": -1}, "n must be at least 1"),
        ({"std": float("nan")}, "std must be a finite number >= 0"),
        ({"support": "postive"}, "support must be 'positive', 'unit' or 'real'"),
    ):
        with pytest.raises(ValueError, match=f"contract_values: {said}"):
            acceptance.contract_values(**{"n": 10, "mean": 1.8, "std": 0.3, **kw})
    np.testing.assert_allclose(np.mean(acceptance.contract_values(1000, 1.8, 0.3)), 1.8, rtol=1e-3)
    with pytest.raises(ValueError, match="synthetic_field: n must be at least 1"):
        acceptance.synthetic_field(0)
    with pytest.raises(ValueError, match="synthetic_field: cluster_size must be at most 10"):
        acceptance.synthetic_field(10, cluster_size=20)
