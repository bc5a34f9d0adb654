"""Problems rounds 15 and 16 found and left, now fixed.

``discover --report figs/heldout_per_step.png --figures figs`` wrote the report, then
the figure of that name over it (exit 0): the figures' names depend on the run (steps,
effects, variables), so no other command's check of the files written inside an output
folder covered them. ``robust_std`` of no value was NaN with a RuntimeWarning and of one
NaN value NaN, after which ``outliers`` flagged nothing at all; ``beam_sigma`` squared a
negative RMS away (a tracking error of -2 mrad passed for 2); ``confidence_intervals`` of
values holding a NaN returned NaN intervals (normal) or failed inside SciPy (bootstrap);
a bytes path given to a PAINT or acceptance reader failed inside ``pathlib`` with a
TypeError naming no argument.

Ill-typed values are given under the ``unchecked`` fixture.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np
import pytest
from helpers import run_cli

import heliojax as hj
from heliojax import acceptance, paint
from heliojax.cli import _discover
from heliojax.discovery._report import FIGURE_NAME_PATTERN


@pytest.mark.parametrize(
    ("flag", "name"),
    [
        ("--report", "heldout_per_step.png"),
        ("--markdown", "screen_step1.png"),
        ("--report", "residuals_step2_wind.png"),
    ],
)
def test_discover_refuses_an_output_named_like_one_of_its_figures(tmp_path, capsys, monkeypatch, flag, name):
    monkeypatch.chdir(tmp_path)
    rc, _, err = run_cli(["discover", flag, f"figs/{name}", "--figures", "figs", "--quiet"], capsys)
    assert rc == 2 and flag in err and name in err and "--figures" in err, err
    assert not (tmp_path / "figs").exists()  # refused before any work


def test_every_figure_discover_writes_has_a_name_of_the_pattern():
    """The pattern the check uses covers every name ``write_figures`` gives (its docstring
    lists them); other files in the folder are not taken for figures."""
    for name in (
        "heldout_per_step.png",
        "screen_step12.png",
        "residuals_step3_encoder_wobble.png",
        "unexplained_1_wind_direction.png",
        "change_points.png",
    ):
        assert FIGURE_NAME_PATTERN.fullmatch(name), name
    for name in ("report.json", "discovery.md", "screen_step.png", "heldout_per_step.png.json"):
        assert not FIGURE_NAME_PATTERN.fullmatch(name), name


def test_a_report_beside_the_figures_under_another_name_is_no_clash(tmp_path):
    args = argparse.Namespace(figures=tmp_path / "figs", report=tmp_path / "figs" / "report.json", markdown=None)
    assert _discover.outputs_inside(args) == []
    args.report = tmp_path / "figs" / "change_points.png"
    assert _discover.outputs_inside(args) == [("figures", tmp_path / "figs" / "change_points.png")]


def test_robust_std_needs_finite_values_and_outliers_judge_the_measured_ones():
    with pytest.raises(ValueError, match="robust_std: needs finite values, got no values"):
        acceptance.robust_std(np.zeros(0))
    with pytest.raises(ValueError, match="1 NaN or infinite"):
        acceptance.robust_std(np.array([1.0, np.nan, 2.0]))
    assert acceptance.robust_std(np.array([1.0, 2.0, 3.0])) == pytest.approx(1.4826)
    # an unmeasured heliostat among the values: the others are still judged (before, nothing was flagged)
    values = np.array([1.0, 1.1, 0.9, 1.05, 0.95, np.nan, 9.0])
    assert acceptance.outliers(values, 3.0, "high").tolist() == [False] * 6 + [True]
    assert not acceptance.outliers(np.full(3, np.nan), 3.0).any()


def test_beam_sigma_refuses_a_negative_or_nan_rms_and_still_traces():
    with pytest.raises(ValueError, match="tracking_mrad must be finite and >= 0"):
        acceptance.beam_sigma(-2.0, 1.0)
    with pytest.raises(ValueError, match="slope_mrad"):
        acceptance.beam_sigma(np.array([1.0, 2.0]), np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="sun_sigma_mrad"):
        acceptance.beam_sigma(1.0, 1.0, -4.65)
    plain = acceptance.beam_sigma(np.array([2.0, 0.0]), np.array([1.0, 1.0]))
    traced = jax.jit(acceptance.beam_sigma)(np.array([2.0, 0.0]), np.array([1.0, 1.0]))
    np.testing.assert_allclose(traced, plain, rtol=1e-12)
    assert float(plain[1]) == pytest.approx(1e-3 * np.sqrt(acceptance.SUN_SIGMA_MRAD**2 + 2.0), rel=1e-6)


@pytest.mark.parametrize("method", ["normal", "bootstrap"])
def test_confidence_intervals_refuse_nan_values(method):
    with pytest.raises(ValueError, match="1 of 4 values are NaN or infinite"):
        acceptance.confidence_intervals(np.array([1.0, 2.0, np.nan, 3.0]), 0.95, method, n_resamples=50)
    # level1_test drops the unmeasured values itself, as documented
    result = acceptance.level1_test(np.array([1.0, 2.0, np.nan, 3.0]), 2.0)
    assert result.n == 3


def test_a_bytes_path_is_a_type_error_naming_the_argument(tmp_path, unchecked):
    with pytest.raises(TypeError, match="path: expected a directory path .* got bytes"):
        hj.load_paint_directory(bytes(hj.default_data_dir()))  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match="paint_dir: expected a str path, got bytes"):
        acceptance.positions_from_paint(b"paint")  # pyright: ignore[reportArgumentType]
    with pytest.raises(TypeError, match="got bytes"):
        paint.read_heliostat_properties(b"x.json")  # pyright: ignore[reportArgumentType]
