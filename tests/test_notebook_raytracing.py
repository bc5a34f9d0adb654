"""Execute notebooks/raytracing.ipynb (stored without outputs) with nbclient."""

from _notebooks import run_notebook


def test_notebook_raytracing_runs(tmp_path, monkeypatch):
    _, text, _ = run_notebook("raytracing.ipynb", tmp_path, monkeypatch)
    assert "Mrays/s" in text
    assert "normal RMS error vs truth" in text
