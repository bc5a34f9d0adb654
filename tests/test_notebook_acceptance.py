"""Execute notebooks/acceptance.ipynb (stored without outputs) with nbclient."""

from _notebooks import run_notebook


def test_notebook_acceptance_runs(tmp_path, monkeypatch):
    _, text, _ = run_notebook("acceptance.ipynb", tmp_path, monkeypatch)
    assert "LEVEL 1: FAIL" in text
    assert "cluster 1:" in text
