"""Execute notebooks/real_surfaces.ipynb (stored without outputs) with nbclient."""

import pytest
from _notebooks import run_notebook
from conftest import SHARED_PAINT


def test_notebook_real_surfaces_runs(tmp_path, monkeypatch):
    if not (SHARED_PAINT.parent / "artist-scenarios").exists():
        pytest.skip("needs ../shared/data (ARTIST scenarios and PAINT flux samples)")
    _, text, n_images = run_notebook("real_surfaces.ipynb", tmp_path, monkeypatch)
    assert "round trip: largest control-point change 0.0e+00 m" in text
    assert "deflectometry surface closer in KL on 3 of 3 images" in text
    assert "(held out): KL ideal" in text
    assert n_images >= 3  # scene trace, records figure, deviation map
