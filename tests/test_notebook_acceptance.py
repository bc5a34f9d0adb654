"""Execute notebooks/acceptance.ipynb (stored without outputs) with nbclient."""

from _notebooks import run_notebook


def test_notebook_acceptance_runs(tmp_path, monkeypatch):
    # the typical year at 3 h steps instead of 1 h
    _, text, _ = run_notebook("acceptance.ipynb", tmp_path, monkeypatch, overrides={"year_step_minutes": 180})
    assert "LEVEL 1: FAIL" in text
    assert "cluster 1:" in text
