"""Execute notebooks/calibration.ipynb (stored without outputs) with nbclient on the embedded data."""

from _notebooks import run_notebook


def test_calibration_notebook_runs(tmp_path, monkeypatch):
    monkeypatch.delenv("HELIOJAX_NOTEBOOK_DATA", raising=False)
    _, text, n_images = run_notebook("calibration.ipynb", tmp_path, monkeypatch)
    assert "5 heliostats" in text
    assert "actuator  converged 5/5" in text  # BL14 (6 training records) calibrated by fleet pooling
    assert n_images >= 3
