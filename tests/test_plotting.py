"""The calibration figure marks what the summary flags."""

from __future__ import annotations

import types

import matplotlib
import numpy as np

from heliojax._plotting import plot_calibration

matplotlib.use("Agg")


def _run(flags: dict[str, dict]):
    ids = ["A", "B", "C"]
    rng = np.random.default_rng(0)
    heliostats = {
        h: {
            "status": "converged",
            "uncalibrated_test_rms_mrad": 20.0,
            "train_rms_mrad": 0.8,
            "test_rms_mrad": 1.2,
            "change_point": None,
            "worse_than_nominal": False,
            **flags.get(h, {}),
        }
        for h in ids
    }
    mask = np.ones((3, 4), bool)
    return types.SimpleNamespace(
        summary={"heliostats": heliostats, "model": "actuator", "split": "time"},
        test_mask=mask,
        fleet=types.SimpleNamespace(mask=mask),
        outlier=np.zeros_like(mask),
        residuals_mrad=rng.normal(size=(3, 4, 2)),
        uncalibrated_residuals_mrad=rng.normal(scale=10.0, size=(3, 4, 2)),
        errors_mrad=np.tile([1.0, 2.0, 3.0, 4.0], (3, 1)),
        uncalibrated_mrad=np.tile([10.0, 20.0, 30.0, 40.0], (3, 1)),
    )


def test_panel_titles_count_the_beam_errors_summary_json_counts():
    """The scatter panels' titles took the median and RMS of the two plotted components
    (48.93 against summary.json's 49.06 mrad in a trial) and, after calibration, over
    heliostats that were not calibrated too: now the beam errors over the same records
    as summary.json's fleet figures, with their number."""
    fig = plot_calibration(_run({"C": {"status": "max_steps"}}))
    before, after = fig.axes[1].get_title(), fig.axes[2].get_title()
    assert "12 records: median 25.00, RMS 27.39 mrad" in before, before  # sqrt(mean(100, 400, 900, 1600))
    assert "8 records: median 2.50, RMS 2.74 mrad" in after, after  # C left out


def _legend(fig) -> list[str]:
    legend = fig.axes[0].get_legend()
    return [t.get_text() for t in legend.get_texts()]


def test_change_points_and_worse_than_nominal_are_marked():
    flags = {"B": {"change_point": {"time": "2023-05-27T10:15:25Z"}}, "C": {"worse_than_nominal": True}}
    fig = plot_calibration(_run(flags))
    labels = _legend(fig)
    assert any(label.startswith("change point") for label in labels)
    assert any(label.startswith("worse than nominal") for label in labels)
    # the marks sit over the flagged heliostats' bars
    offsets = [c.get_offsets() for c in fig.axes[0].collections if len(c.get_offsets())]
    assert sorted(float(o[0, 0]) for o in offsets) == [1.0, 2.0]


def test_noise_outliers_are_marked():
    """A heliostat named a noise outlier (garbage records: its fit is reported, the fleet's
    statistics leave it out) was drawn like any calibrated one; it is marked now."""
    fig = plot_calibration(_run({"A": {"noise_outlier": True}, "C": {"noise_outlier": True}}))
    assert any(label.startswith("noise outlier") for label in _legend(fig))
    offsets = [c.get_offsets() for c in fig.axes[0].collections if len(c.get_offsets())]
    assert sorted(float(x) for o in offsets for x in o[:, 0]) == [0.0, 2.0]


def test_heliostats_under_the_small_fleet_prior_are_marked():
    """A few-record heliostat calibrated under the small-fleet prior (the fleet too small
    to learn a prior) rests on the declared typical sizes and one or two heliostats: the
    figure says so, not only the summary."""
    fig = plot_calibration(_run({"B": {"small_fleet_prior": True}}))
    assert any(label.startswith("small-fleet prior") for label in _legend(fig))
    offsets = [c.get_offsets() for c in fig.axes[0].collections if len(c.get_offsets())]
    assert sorted(float(x) for o in offsets for x in o[:, 0]) == [1.0]


def test_nothing_flagged_nothing_marked():
    fig = plot_calibration(_run({}))
    assert not any(label.startswith(("change point", "worse than", "small-fleet")) for label in _legend(fig))


def test_plan_figure_keeps_a_readable_width_for_large_fleets(tmp_path):
    from heliojax._plotting import plot_plan, save_figure

    rng = np.random.default_rng(1)
    h, k = 300, 4
    before = rng.uniform(0.5, 5.0, h)
    after = before[:, None] * np.linspace(0.8, 0.4, k)[None, :]
    chosen = np.tile(np.arange(k), (h, 1))
    changed = np.zeros(h, bool)
    changed[np.argmax(before)] = True
    fig = plot_plan([f"H{i:03d}" for i in range(h)], before, after, chosen, changed)
    assert fig.get_size_inches()[0] < 20.0
    bars = fig.axes[0]
    assert len(bars.get_xticklabels()) == 40 and "40 of 300" in bars.get_xlabel()
    save_figure(fig, tmp_path / "plan.png")  # the render check of every saved figure runs here
    assert (tmp_path / "plan.png").stat().st_size > 10_000


def test_aim_figure_says_when_every_command_is_flagged(tmp_path):
    """An aim day on which every command was flagged drew two empty panels and an empty
    legend box: both panels now say that nothing is usable and where to look."""
    from heliojax._plotting import plot_aim, save_figure

    cov = np.tile(np.eye(2), (3, 4, 1, 1))
    fig = plot_aim(["A", "B", "C"], cov, np.zeros((3, 4), bool), np.full(3, 100.0))
    for ax in fig.axes:
        assert any("no usable command" in t.get_text() for t in ax.texts)
        assert ax.get_legend() is None
    save_figure(fig, tmp_path / "aim.png")
    usable = plot_aim(["A", "B", "C"], cov, np.ones((3, 4), bool), np.full(3, 100.0))
    assert not any(t.get_text() for ax in usable.axes for t in ax.texts)
    assert usable.axes[1].get_legend() is not None
