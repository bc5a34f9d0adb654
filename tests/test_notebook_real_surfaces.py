"""Execute notebooks/real_surfaces.ipynb (stored without outputs) with nbclient."""

import re

import numpy as np
import pytest
from _notebooks import run_notebook
from conftest import SHARED_PAINT


@pytest.mark.optimised(kernel_only=True)  # the kernel compiles, not this process
def test_notebook_real_surfaces_runs(tmp_path, monkeypatch):
    if not (SHARED_PAINT.parent / "artist-scenarios").exists():
        pytest.skip("needs ../shared/data (ARTIST scenarios and PAINT flux samples)")
    # a coarser scene picture and 25 reconstruction steps instead of 60 (the forward
    # validation, section 2, runs as in the notebook)
    overrides = {"scene_resolution": (16, 16), "reconstruction_steps": 25}
    _, text, n_images = run_notebook("real_surfaces.ipynb", tmp_path, monkeypatch, overrides=overrides)
    assert "round trip: largest control-point change 0.0e+00 m" in text
    # forward validation on AA39's three images (pointing corrected): the deflectometry
    # surface matches every measured spot better than ideal facets (NCC and KL) and its
    # second-moment widths agree with the measured ones to 10 %
    rows = re.findall(
        r"^ *(\d+) +(ideal facets|deflectometry) +([\d.]+) +([\d.]+) +([\d.]+) +([\d.]+) +([\d.]+) +([\d.]+)$",
        text,
        re.M,
    )
    assert len(rows) == 6, text
    by = {(r[0], r[1]): [float(x) for x in r[2:]] for r in rows}
    for record in {r[0] for r in rows}:
        ideal, measured = by[(record, "ideal facets")], by[(record, "deflectometry")]
        assert measured[0] > ideal[0] and measured[1] < ideal[1], (record, ideal, measured)
        np.testing.assert_allclose(measured[2:4], measured[4:6], rtol=0.1)
    # reconstruction from two images predicts the held-out third better than ideal facets
    held = re.search(r"\(held out\): KL ideal ([\d.]+), reconstructed ([\d.]+)", text)
    assert held is not None, text
    assert float(held.group(2)) < 0.7 * float(held.group(1))
    assert n_images >= 3  # scene trace, records figure, deviation map
