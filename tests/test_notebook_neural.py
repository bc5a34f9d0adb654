"""Execute notebooks/neural.ipynb (stored without outputs) with nbclient."""

from _notebooks import run_notebook


def test_notebook_neural_runs(tmp_path, monkeypatch):
    _, text, _ = run_notebook("neural.ipynb", tmp_path, monkeypatch)
    assert "fleet held-out median LM+residual" in text
    assert "networks without the fallback rule" in text
    assert "notebook ran in" in text
