"""Threaded batching (blocks of lanes, one program call per host thread) against
the one-call strategy it wraps: the same numbers bit for bit, for the fit core
(plain, ahead of time, only some heliostats) and for discovery's lanes engine;
how lanes are shared out into blocks."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from helpers import zoo

import heliojax as hj
from heliojax.discovery import _lanes, simulate_fleet
from heliojax.effects import make_effect

# three blocks of two or three lanes: the last block is padded (8 lanes = 3 x 3 - 1)
THREE_SMALL_BLOCKS = hj.Threaded(hj.LaxMap(), workers=3, min_block=2)


def _leaves_equal(a, b) -> None:
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_blocks_take_every_bth_lane_and_fall_back_to_one_call():
    t = hj.Threaded(hj.LaxMap(), workers=3, min_block=2)
    assert [t.n_blocks(n) for n in (1, 3, 4, 5, 6, 8, 100)] == [1, 1, 2, 2, 3, 3, 3]
    lanes = (np.arange(8), np.arange(16).reshape(8, 2))
    blocks = t._blocks(lanes)
    assert [b[0].tolist() for b in blocks] == [[0, 3, 6], [1, 4, 7], [2, 5, 0]]  # padded with lane 0
    assert t.block(lanes)[1].shape == (3, 2)
    # a run joins the blocks back in lane order and strips the padding
    calls = []

    def program(scale, x, y):
        calls.append(x.shape)
        return {"x": x * scale, "y": y}

    out = t.run(program, (10,), lanes)
    assert calls == [(3,)] * 3
    np.testing.assert_array_equal(out["x"], 10 * np.arange(8))
    np.testing.assert_array_equal(out["y"], lanes[1])
    # too few lanes for two blocks: one plain call
    calls.clear()
    t.run(program, (1,), (np.arange(3), np.zeros((3, 2))))
    assert calls == [(3,)]
    assert hj.fitting.batching_from_name("threaded") == hj.Threaded(hj.LaxMap())
    assert hj.Threaded().skips_inactive and not hj.Threaded(hj.Vmap()).skips_inactive


@pytest.mark.parametrize(
    "kwargs, message",
    [({"workers": 0}, "workers"), ({"min_block": 0}, "min_block"), ({"inner": hj.Threaded()}, "inner")],
)
def test_bad_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        hj.Threaded(**kwargs)


def test_threaded_fit_equals_lax_map_bit_for_bit():
    """Blocks are independent lanes of the same per-heliostat program: parameters,
    statuses, costs and covariances equal those of one ``lax.map`` call exactly,
    also ahead of time (:class:`heliojax.fitting.CompiledFit`) with only some
    heliostats fitted."""
    fleet = zoo("stone").fleet
    model0 = hj.StoneModel.nominal(fleet.counts.dtype)
    ref = hj.fit(model0, fleet, batching=hj.LaxMap())
    _leaves_equal(hj.fit(model0, fleet, batching=THREE_SMALL_BLOCKS), ref)
    only = np.arange(fleet.n_heliostats) % 3 != 1
    outs = []
    for batching in (hj.LaxMap(), THREE_SMALL_BLOCKS):
        compiled = hj.fitting.CompiledFit(model0, fleet, batching=batching)
        first = compiled(model0)
        outs.append((first, compiled(first.model, only=only, otherwise=ref)))
    _leaves_equal(outs[0], outs[1])


def test_threaded_discovery_lanes_equal_lax_map_bit_for_bit():
    """Discovery's lane programs (expansion, fit, Jacobian, residuals) in blocks,
    with a subset of lanes active: the same arrays as one call."""
    fleet, _ = simulate_fleet(3, 3, 40, effects=(make_effect("backlash"),), noise_mrad=0.25)
    layout, template = _lanes.make_layout(hj.nominal_model("stone8"), ("backlash",), fleet)
    lanes = _lanes.make_lanes(fleet, 3)
    n_lanes = lanes.fold.shape[0]
    p0 = np.broadcast_to(np.asarray(layout.view.to_vector(template)), (n_lanes, layout.view.n_parameters))
    active = lanes.fold != 1

    def run(batching):
        engine = _lanes.Engine.create(layout, template, lanes, batching=batching)
        expansion = engine.expand(p0, active=active)
        out = engine.fit(p0, [0, 1], p0, expansion, active=active)
        p = np.asarray(out["params"])
        again = engine.fit(p, [0, 1], p, engine.expand(p, derivative_from=expansion, active=active), active=active)
        results = (out, again, engine.jacobian(p, active=active), engine.residuals(p, evaluate=True, active=active))
        return len(engine.groups), results

    n_ref, ref = run(hj.LaxMap())
    n_blocks, threaded = run(THREE_SMALL_BLOCKS)
    assert (n_ref, n_blocks) == (1, 3)  # one group of 12 lanes, cut into three blocks
    assert np.any(ref[0]["ok"]) and not np.all(ref[0]["ok"])  # the inactive lanes are left out
    _leaves_equal(threaded, ref)


def test_threaded_robust_fit_and_residuals_equal_lax_map_bit_for_bit():
    """The robust fit's passes and its residual evaluations between them in blocks:
    weights, flags, noise and parameters as with one call."""
    fleet = zoo("backlash").fleet
    model0 = hj.ActuatorModel.nominal(fleet.counts.dtype)
    ref = hj.fitting.fit_robust(model0, fleet, batching=hj.LaxMap())
    got = hj.fitting.fit_robust(model0, fleet, batching=THREE_SMALL_BLOCKS)
    for name in ("weights", "outlier", "noise_mrad", "scale_mrad"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(ref, name)))
    _leaves_equal(got.solution, ref.solution)
    r_ref = hj.fleet_residuals_mrad(ref.solution.model, fleet)
    r_got = hj.fleet_residuals_mrad(ref.solution.model, fleet, batching=THREE_SMALL_BLOCKS)
    assert r_got.shape == r_ref.shape == fleet.counts.shape
    np.testing.assert_array_equal(np.asarray(r_got), np.asarray(r_ref))
