"""Execute notebooks/discovery.ipynb (stored without outputs) with nbclient."""

from _notebooks import run_notebook


def test_notebook_discovery_runs(tmp_path, monkeypatch):
    _, text, n_images = run_notebook("discovery.ipynb", tmp_path, monkeypatch)
    assert "named: ['backlash', 'thermal']" in text or "named: ['thermal', 'backlash']" in text
    assert "named on the real records: ['actuator_geometry'" in text
    assert n_images >= 3
