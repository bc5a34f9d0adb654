"""Surface reconstruction from synthetic flux images of a hidden deformed surface."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heliojax._geometry import TargetPlane
from heliojax.optics import FacetLayout, ImageGrid, NurbsFacets, PillboxSun, aim_pose, flux_images
from heliojax.optics._reconstruct import normal_rms_error_mrad, reconstruct_surface, with_height_offsets


def scene():
    f = 200.0  # weak canting: facet images stay distinguishable on the target
    cent = np.array([[-0.81, 0.645], [0.81, 0.645], [-0.81, -0.645], [0.81, -0.645]])
    ce = np.array([[0.8, 0, c[0] / (2 * f) * 0.8] for c in cent])
    cn = np.array([[0, 0.64, c[1] / (2 * f) * 0.64] for c in cent])
    layout = FacetLayout.from_arrays(np.c_[cent, np.zeros(4)], ce, cn)
    ideal = NurbsFacets.ideal(layout, n_ctrl=(5, 5), degree=3)
    rng = np.random.default_rng(1)
    g = np.linspace(-1, 1, 5)
    X, Y = np.meshgrid(g, g, indexing="ij")
    dz = np.zeros((4, 5, 5))
    for k in range(4):
        bx, by = rng.uniform(-0.5, 0.5, 2)
        amp = rng.uniform(0.6e-3, 1.2e-3) * rng.choice([-1, 1])
        dz[k] = amp * np.exp(-((X - bx) ** 2 + (Y - by) ** 2) / 0.5)
    truth = with_height_offsets(ideal, jnp.asarray(dz))
    target = TargetPlane.from_corners(
        np.array([2.5, 0, 22.5]),
        np.array([-2.5, 0, 22.5]),
        np.array([2.5, 0, 17.5]),
        np.array([-2.5, 0, 17.5]),
    )
    grid = ImageGrid.for_target(target, (64, 64))
    centre = jnp.asarray([0.0, 40.0, 2.0])
    suns, poses = [], []
    for az, el in [(-60, 30), (-30, 45), (0, 60), (30, 45), (60, 30), (0, 25)]:
        a, e = np.deg2rad(az), np.deg2rad(el)
        s = jnp.asarray([np.cos(e) * np.sin(a), -np.cos(e) * np.cos(a), np.sin(e)])
        suns.append(s)
        poses.append(aim_pose(centre, s, target.centre))
    suns = jnp.stack(suns)
    poses = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *poses)
    return ideal, truth, target, grid, suns, poses


@pytest.mark.optimised
def test_reconstruction_recovers_hidden_bumps():
    ideal, truth, target, grid, suns, poses = scene()
    # the hidden deformation: bumps with 1-3 mrad maximum slope
    st, si = truth.evaluate((24, 24)), ideal.evaluate((24, 24))
    ang = np.arccos(np.clip(np.sum(np.asarray(st.normals) * np.asarray(si.normals), -1), -1, 1)) * 1e3
    assert 1.0 <= ang.max() <= 3.0, ang.max()
    n = suns.shape[0]
    surf = truth.evaluate((16, 16))
    surfs = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), surf)
    images = flux_images(
        jax.random.key(99), surfs, poses, suns, target, grid, PillboxSun(), rays_per_point=256, steps=4
    )
    res = reconstruct_surface(
        jax.random.key(0),
        ideal,
        images,
        poses,
        suns,
        target,
        grid,
        PillboxSun(),
        steps=120,
        learning_rate=2.5e-4,
        rays_per_point=32,
    )
    assert res.losses[-20:].mean() < 0.5 * res.losses[0]
    e_ideal = normal_rms_error_mrad(ideal, truth)
    e_rec = normal_rms_error_mrad(res.facets, truth)
    assert e_rec <= e_ideal / 3, (e_rec, e_ideal)
