"""Execute notebooks/raytracing.ipynb (stored without outputs) with nbclient."""

from _notebooks import run_notebook
from conftest import SHARED_PAINT


def test_notebook_raytracing_runs(tmp_path, monkeypatch):
    _, text, n_images = run_notebook("raytracing.ipynb", tmp_path, monkeypatch)
    assert "Mrays/s" in text
    assert "normal RMS error vs truth" in text
    assert n_images >= 3  # figures are shown inline (no forced Agg backend)
    if (SHARED_PAINT / "WRI1030197-tower-measurements.json").exists():  # found beside the checkout
        assert "shared PAINT data not found" not in text
