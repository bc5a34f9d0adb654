"""Surface reconstruction on PAINT's real flux images (AA39: 3 records)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHARED_PAINT

from heliojax.optics import (
    BuieSun,
    NurbsFacets,
    centroid,
    flux_images,
    flux_records,
    flux_sample_records,
    with_height_offsets,
)

SUN = BuieSun(0.05)


@pytest.fixture(scope="module")
def aa39():
    pairs = [p for p in flux_sample_records(SHARED_PAINT / "flux-samples") if p[1].parent.parent.name == "AA39"]
    if len(pairs) < 3:
        pytest.skip("needs the AA39 flux samples of ../shared/data/paint")
    return flux_records(pairs, SHARED_PAINT / "WRI1030197-tower-measurements.json", pixels=32)


@eqx.filter_jit
def _trace(facets, recs, key, dtype=jnp.float32, rays=64, resolution=(16, 16)):
    n = recs.images.shape[0]
    surfs = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), facets.evaluate(resolution))
    return flux_images(
        key, surfs, recs.poses, recs.suns, recs.targets, recs.grids, SUN, rays_per_point=rays, dtype=dtype
    )


def test_flux_records_put_the_traced_spot_on_the_measured_one(aa39):
    assert aa39.record_ids == (270398, 271633, 275564) and aa39.images.shape == (3, 32, 32)
    ideal = NurbsFacets.ideal(aa39.layout)
    img = _trace(ideal, aa39, jax.random.key(0))
    c = np.asarray(centroid(img.astype(jnp.float64), aa39.grids))
    centre = np.stack(
        [
            (np.asarray(aa39.grids.u_min) + np.asarray(aa39.grids.u_max)) / 2,
            (np.asarray(aa39.grids.v_min) + np.asarray(aa39.grids.v_max)) / 2,
        ],
        -1,
    )
    # the window is centred on the measured centroid; the pose on the record's focal spot
    assert np.all(np.linalg.norm(c - centre, axis=-1) < 0.15)


def test_gradient_through_the_real_scene_matches_finite_differences(aa39):
    """float64 tracer over the three real records (targets, suns, corrected poses):
    d loss / d control-point heights against central differences."""
    ideal = NurbsFacets.ideal(aa39.layout, n_ctrl=(4, 4))
    key = jax.random.key(3)
    u, v = (np.asarray(x) for x in aa39.grids.pixel_centres())
    centre_u, centre_v = u.mean(-1), v.mean(-1)
    weight = jnp.asarray(
        np.exp(
            -((u[:, None, :] - centre_u[:, None, None] - 0.3) ** 2 + (v[:, :, None] - centre_v[:, None, None]) ** 2)
            / 0.8
        )
    )

    @jax.jit
    def loss(dz):
        img = _trace(with_height_offsets(ideal, dz), aa39, key, dtype=jnp.float64, rays=8, resolution=(6, 6))
        return jnp.sum(img * weight) * 1e-4

    dz0 = jnp.asarray(np.random.default_rng(0).normal(0, 1e-3, ideal.control_points.shape[:-1]))
    g = np.asarray(jax.grad(loss)(dz0))
    assert np.abs(g).max() > 0
    h = 1e-7
    for idx in [(0, 1, 1), (1, 2, 1), (2, 0, 3), (3, 2, 2)]:
        e = jnp.zeros_like(dz0).at[idx].set(h)
        fd = (float(loss(dz0 + e)) - float(loss(dz0 - e))) / (2 * h)
        assert g[idx] == pytest.approx(fd, rel=2e-3, abs=1e-3 * np.abs(g).max())


def test_reconstruct_command_on_real_records(tmp_path, capsys):
    """`heliojax reconstruct --paint ... --heliostat AA39 --held-out ...` writes its
    report, control points and figure, and names a held-out id it does not know."""
    import json

    from heliojax.cli._main import main

    paint = SHARED_PAINT / "flux-samples"
    if not (paint / "AA39").exists():
        pytest.skip("needs ../shared/data/paint/flux-samples")
    out = tmp_path / "aa39"
    argv = ["reconstruct", "--paint", str(paint), "--heliostat", "AA39", "--out", str(out), "--quiet"]
    assert main([*argv, "--held-out", "270398", "--steps", "3", "--rays-per-point", "4"]) == 0
    report = json.loads((out / "reconstruction.json").read_text())
    roles = {r["record"]: r["role"] for r in report["records"]}
    assert roles == {270398: "held out", 271633: "train", 275564: "train"}
    assert (out / "control_points.h5").stat().st_size > 0 and (out / "reconstruction.png").stat().st_size > 0
    capsys.readouterr()
    assert main([*argv, "--held-out", "1"]) == 2
    assert "--held-out [1]" in capsys.readouterr().err
