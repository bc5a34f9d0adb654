"""heliojax.neural: networks, zero-init residual = physics model, the paper variant's
error metric, determinism, vmapped == per-heliostat training, padding invariance,
the fallback rule. Small synthetic problems (the notebook test runs real data)."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from heliojax._beam import beam_pointing_error
from heliojax._geometry import sun_direction
from heliojax._heliostat import RecordContext
from heliojax._kinematics import ActuatorModel, StoneModel, forward, inverse_aim
from heliojax._simulate import calibration_target, synthetic_geometry
from heliojax.fitting import beam_errors_mrad
from heliojax.neural import (
    MLP,
    NeuralConfig,
    NeuralCorrection,
    PaperPredictor,
    fallback_rule,
    heliostat_keys,
    init_networks,
    init_residual_networks,
    paper_beam_error,
    validation_tail,
    zero_correction,
)
from heliojax.neural._train import (
    _finetune_paper_program,
    _finetune_residual_program,
    _pretrain_paper_program,
    _weighted_indices,
    synthetic_fleet_data,
)

H, M = 3, 20
SMALL = NeuralConfig(
    n_synthetic=160,
    pretrain_epochs=6,
    batch_size=32,
    steps_per_epoch=4,
    finetune_epochs=15,
    residual_epochs=40,
    residual_lr=1e-2,
)


@functools.cache
def _problem(h=H, m=M, seed=0):
    """Heliostats that truly follow the actuator law, described by a nominal Stone
    model (whose linear counts-to-angle map misses the law's curvature)."""
    return dict(_problem_arrays(h, m, seed))


@eqx.filter_jit
def _inverse_all(truth, geometry, aim, sun):
    return jax.vmap(lambda g, s: jax.vmap(lambda si: inverse_aim(truth, g, aim, si))(s))(geometry, sun)


def _problem_arrays(h, m, seed):
    key = jax.random.key(seed)
    k_g, k_az, k_el = jax.random.split(key, 3)
    geometry = synthetic_geometry(k_g, h)
    target = calibration_target()
    az = jax.random.uniform(k_az, (h, m), minval=-1.2, maxval=1.2)
    el = jax.random.uniform(k_el, (h, m), minval=0.3, maxval=1.1)
    sun = sun_direction(az, el)
    truth = ActuatorModel.nominal(jnp.float64)
    aim = target.centre + jnp.asarray([0.4, 0.0, -0.3])
    counts = _inverse_all(truth, geometry, aim, sun)
    focal = jnp.broadcast_to(aim, (h, m, 3))
    context = RecordContext.from_sun(sun)
    base = jax.vmap(lambda _: StoneModel.nominal(jnp.float64))(jnp.arange(h))
    mask = np.ones((h, m), bool)
    fit, val = validation_tail(mask, 0.25)
    u = jnp.broadcast_to(target.u_axis, (h, m, 3))
    v = jnp.broadcast_to(target.v_axis, (h, m, 3))
    return tuple(
        dict(
            geometry=geometry, counts=counts, context=context, focal=focal, base=base, fit=fit, val=val, u=u, v=v
        ).items()
    )


def _take(tree, idx):
    return jax.tree_util.tree_map(lambda x: x[idx], tree)


def _residual(p, seed=1, config=SMALL):
    h = p["counts"].shape[0]
    nets = init_residual_networks(jax.random.key(seed), h, config)
    scale = jnp.full((h,), 5e-3)
    keys = heliostat_keys(jax.random.key(seed + 1), h)
    return _finetune_residual_program(
        keys,
        nets,
        p["base"],
        p["geometry"],
        p["counts"],
        p["context"],
        p["focal"],
        scale,
        jnp.asarray(p["fit"], float),
        jnp.asarray(p["val"], float),
        config,
    ), scale


def _tree_equal(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    return len(la) == len(lb) and all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb))


def _tree_close(a, b, rtol=1e-4, atol=1e-6):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


# ------------------------------------------------------------------------------ networks


def test_mlp_shapes_selu_and_lecun_init():
    init = eqx.filter_jit(MLP.init)
    net = init(jax.random.key(0), (5, 6, 5, 4, 3, 1))
    assert net.sizes == (5, 6, 5, 4, 3, 1)
    assert net(jnp.ones(5)).shape == (1,)
    # hand computation: selu hidden layers, linear output
    x = jnp.arange(5.0, dtype=jnp.float32) / 5
    h = x
    for w, b in zip(net.weights[:-1], net.biases[:-1]):
        h = 1.0507009873554805 * np.where(w @ h + b > 0, w @ h + b, 1.6732632423543772 * (np.exp(w @ h + b) - 1))
    np.testing.assert_allclose(net(x), net.weights[-1] @ h + net.biases[-1], rtol=1e-5)
    # LeCun normal: variance 1 / fan_in (a wide layer to estimate it)
    wide = init(jax.random.key(1), (400, 300, 1))
    var = float(np.var(np.asarray(wide.weights[0])))
    assert abs(var * 400 - 1.0) < 0.05
    assert np.all(np.asarray(wide.biases[0]) == 0)


def test_zero_output_network_is_exactly_zero_and_stacks_are_independent():
    nets = eqx.filter_jit(init_networks)(jax.random.key(0), (4,), (2, 6, 5, 4, 3, 2), zero_output=True)
    out = eqx.filter_jit(jax.vmap(lambda n: n(jnp.array([0.3, -0.7]))))(nets)
    assert np.all(np.asarray(out) == 0.0)
    w0 = np.asarray(nets.weights[0])
    assert not np.allclose(w0[0], w0[1])  # different keys per entry
    single = eqx.filter_jit(MLP.init)(jax.random.fold_in(jax.random.key(0), 2), (2, 6, 5, 4, 3, 2), zero_output=True)
    assert _tree_equal(_take(nets, 2), single)


def test_weighted_indices_ignore_zero_weights_and_padding():
    key = jax.random.key(3)
    w = jnp.array([0.0, 1.0, 1.0, 0.0, 1.0])
    idx = np.asarray(_weighted_indices(key, w, 500))
    assert set(idx.tolist()) <= {1, 2, 4}
    padded = jnp.concatenate([w, jnp.zeros(7)])
    assert np.array_equal(idx, np.asarray(_weighted_indices(key, padded, 500)))


# ------------------------------------------------------------------------------ models


def test_zero_initialised_residual_is_the_physics_model_exactly():
    p = _problem()
    nets = init_residual_networks(jax.random.key(0), H)
    models = NeuralCorrection(p["base"], nets, jnp.full((H,), 5e-3))
    mask = jnp.ones((H, M), bool)
    e_nn = beam_errors_mrad(models, p["geometry"], p["counts"], p["context"], p["focal"], mask)
    e_lm = beam_errors_mrad(p["base"], p["geometry"], p["counts"], p["context"], p["focal"], mask)
    assert np.array_equal(np.asarray(e_nn), np.asarray(e_lm))
    assert float(jnp.min(e_lm)) > 0.5  # the physics model is visibly wrong here
    g0, m0, b0 = _take(p["geometry"], 0), _take(models, 0), _take(p["base"], 0)
    c = p["counts"][0, 3]
    assert np.array_equal(np.asarray(forward(m0, g0, c).normal), np.asarray(forward(b0, g0, c).normal))
    angles = b0.joint_angles(g0, c)
    assert np.array_equal(np.asarray(m0.counts(g0, angles)), np.asarray(b0.counts(g0, angles)))


def test_residual_inverse_inverts_a_nonzero_correction():
    p = _problem()
    net = MLP.init(jax.random.key(5), (2, 6, 5, 4, 3, 2))  # not zero
    model = NeuralCorrection(_take(p["base"], 0), net, jnp.asarray(2e-3))
    g = _take(p["geometry"], 0)
    c = p["counts"][0, 5]
    assert float(jnp.max(jnp.abs(model.correction(g, c)))) > 1e-4
    back = model.counts(g, model.joint_angles(g, c))
    np.testing.assert_allclose(np.asarray(back), np.asarray(c), atol=1e-3)


def test_paper_metric_equals_beam_error_for_the_physics_models_own_prediction():
    p = _problem()
    g, model = (
        _take(p["geometry"], 1),
        StoneModel(*[jnp.asarray(x) for x in (2e-3, -1e-3, 0.0, 0.0, 5e-3, -4e-3, 1.001, 0.999)]),
    )
    for j in range(4):
        c, s, f = p["counts"][1, j], p["context"].sun[1, j], p["focal"][1, j]
        predicted = inverse_aim(model, g, f, s)
        e_paper = paper_beam_error(model, g, c, predicted, s, f)
        e_beam = beam_pointing_error(forward(model, g, c), s, f)
        assert float(e_beam) > 1e-3
        np.testing.assert_allclose(float(e_paper), float(e_beam), rtol=1e-4)
        assert float(paper_beam_error(model, g, c, c, s, f)) < 1e-9


# ------------------------------------------------------------------------------ training


def test_residual_training_is_deterministic_learns_and_matches_single_heliostat():
    p = _problem()
    (nets, info), scale = _residual(p)
    (nets2, _), _ = _residual(p)
    assert _tree_equal(nets, nets2)
    (nets3, _), _ = _residual(p, seed=7)
    assert not _tree_equal(nets, nets3)
    # it learns the Stone model's missing actuator curvature (validation records)
    models = NeuralCorrection(p["base"], nets, scale)
    val = jnp.asarray(p["val"])
    e_nn = np.asarray(beam_errors_mrad(models, p["geometry"], p["counts"], p["context"], p["focal"], val))
    e_lm = np.asarray(beam_errors_mrad(p["base"], p["geometry"], p["counts"], p["context"], p["focal"], val))
    assert np.nanmedian(e_nn) < 0.7 * np.nanmedian(e_lm)
    # one heliostat alone (same key: fold_in(key, 1)) gives the same network
    q = {k: (_take(v, slice(1, 2)) if k not in ("fit", "val") else v[1:2]) for k, v in p.items()}
    nets_q = init_residual_networks(jax.random.key(1), H, SMALL)
    keys = heliostat_keys(jax.random.key(2), H)
    single, _ = _finetune_residual_program(
        keys[1:2],
        _take(nets_q, slice(1, 2)),
        q["base"],
        q["geometry"],
        q["counts"],
        q["context"],
        q["focal"],
        scale[1:2],
        jnp.asarray(q["fit"], float),
        jnp.asarray(q["val"], float),
        SMALL,
    )
    _tree_close(_take(nets, slice(1, 2)), single)


def test_residual_training_ignores_padded_records_and_heliostats():
    p = _problem()
    (nets, _), scale = _residual(p)
    extra = 5

    def pad_rec(x):
        # padded records hold junk values; zero weight must make them irrelevant
        junk = jnp.full(x.shape[:1] + (extra,) + x.shape[2:], 0.3, x.dtype)
        return jnp.concatenate([x, junk], 1)

    q = dict(p)
    for k in ("counts", "focal"):
        q[k] = pad_rec(p[k])
    q["counts"] = q["counts"].at[:, M:].set(30000.0)
    q["context"] = jax.tree_util.tree_map(pad_rec, p["context"])
    q["fit"] = np.concatenate([p["fit"], np.zeros((H, extra), bool)], 1)
    q["val"] = np.concatenate([p["val"], np.zeros((H, extra), bool)], 1)
    # plus one padding heliostat (copy of heliostat 0, no records)
    q = {
        k: (
            jax.tree_util.tree_map(lambda x: jnp.concatenate([x, x[:1]], 0), v)
            if k not in ("fit", "val")
            else np.concatenate([v, np.zeros((1, v.shape[1]), bool)], 0)
        )
        for k, v in q.items()
    }
    (nets_p, _), _ = _residual(q)
    _tree_close(_take(nets_p, slice(0, H)), nets, rtol=1e-4, atol=1e-6)
    # the padding heliostat's network never moves: still exactly zero output
    out = _take(nets_p, H)(jnp.array([0.1, 0.2]))
    assert np.all(np.asarray(out) == 0.0)


def _paper(p, keys_seed=0, h=None):
    h = p["counts"].shape[0] if h is None else h
    syn = synthetic_fleet_data(
        heliostat_keys(jax.random.key(keys_seed), h),
        p["base"],
        p["geometry"],
        p["context"].sun,
        p["focal"],
        p["u"],
        p["v"],
        jnp.asarray(p["fit"], float),
        SMALL,
    )
    preds, _ = _pretrain_paper_program(heliostat_keys(jax.random.key(keys_seed + 1), h), syn, SMALL)
    tuned, _ = _finetune_paper_program(
        heliostat_keys(jax.random.key(keys_seed + 2), h),
        preds,
        p["counts"],
        p["context"].sun,
        p["focal"],
        jnp.asarray(p["fit"], float),
        jnp.asarray(p["val"], float),
        SMALL,
    )
    return syn, preds, tuned


@pytest.mark.slow
def test_paper_variant_synthetic_data_pretraining_and_determinism():
    p = _problem(h=2)
    syn, preds, tuned = _paper(p)
    # synthetic points are consistent with the physics model: it hits the aim point exactly
    g0, b0 = _take(p["geometry"], 0), _take(p["base"], 0)
    for j in range(3):
        e = beam_pointing_error(forward(b0, g0, syn.counts[0, j]), syn.sun[0, j], syn.spot[0, j])
        assert float(e) < 1e-7
    assert syn.counts.shape == (2, SMALL.n_synthetic, 2)
    assert int(np.sum(np.asarray(syn.is_val[0]))) == SMALL.n_synthetic_val
    assert np.mean(np.asarray(syn.valid)) > 0.9
    # pretraining reduced the loss from the random initialisation
    assert isinstance(preds, PaperPredictor)
    syn2, preds2, tuned2 = _paper(p)
    assert _tree_equal(tuned, tuned2) and _tree_equal(syn, syn2)
    # fine-tuning with lr 1e-5 moves the weights only a little
    dw = np.abs(np.asarray(tuned.networks.weights[0]) - np.asarray(preds.networks.weights[0])).max()
    assert 0 < dw <= SMALL.finetune_lr * SMALL.finetune_epochs * 1.01


@pytest.mark.slow
def test_paper_pretraining_vmapped_equals_single_heliostat():
    p = _problem(h=2)
    _, preds, _ = _paper(p)
    q = {k: (_take(v, slice(1, 2)) if k not in ("fit", "val") else v[1:2]) for k, v in p.items()}
    syn_q = synthetic_fleet_data(
        heliostat_keys(jax.random.key(0), 2)[1:2],
        q["base"],
        q["geometry"],
        q["context"].sun,
        q["focal"],
        q["u"],
        q["v"],
        jnp.asarray(q["fit"], float),
        SMALL,
    )
    single, _ = _pretrain_paper_program(heliostat_keys(jax.random.key(1), 2)[1:2], syn_q, SMALL)
    _tree_close(_take(preds, slice(1, 2)), single)


# ------------------------------------------------------------------------------ rules


def test_validation_tail_takes_the_latest_training_records():
    train = np.array([[1, 1, 0, 1, 1, 1, 0, 1, 0, 1, 1, 0]], bool)  # 8 training records
    fit, val = validation_tail(train, 0.25)
    assert np.flatnonzero(val[0]).tolist() == [9, 10]
    assert np.flatnonzero(fit[0]).tolist() == [0, 1, 3, 4, 5, 7]
    # too few to fit the network on the rest: no validation (-> fallback)
    fit, val = validation_tail(np.array([[1, 1, 0]], bool), 0.25)
    assert not val.any() and fit.sum() == 2


def test_fallback_rule_ten_percent():
    fb, why = fallback_rule(
        nn_val_median=np.array([1.0, 1.10, 1.1001, 0.5, np.nan, 2.0]),
        lm_val_median=np.array([1.0, 1.0, 1.0, 1.0, 1.0, np.nan]),
        tolerance=0.10,
    )
    assert fb.tolist() == [False, False, True, False, True, True]
    assert why[0] is None and "no validation" in why[5] and "not finite" in why[4]


def test_a_network_that_corrects_nothing_falls_back_with_its_reason():
    """A residual network still at its zero initial output (no fine-tuning step beat
    the physics model on validation) is the physics model: a fallback, even though its
    validation median equals the LM model's (within the tolerance)."""
    nets = init_residual_networks(jax.random.key(0), 3)
    models = NeuralCorrection(jax.vmap(lambda _: StoneModel.nominal(jnp.float64))(jnp.arange(3)), nets, jnp.ones(3))
    assert zero_correction(models).tolist() == [True, True, True]
    bias = nets.biases[-1].at[1, 0].set(1e-30)  # any output weight or bias off zero: a correction
    weights = nets.weights[-1].at[2, 1, 0].set(-1e-30)
    moved = eqx.tree_at(lambda m: (m.network.biases[-1], m.network.weights[-1]), models, (bias, weights))
    assert zero_correction(moved).tolist() == [True, False, False]
    fb, why = fallback_rule(np.ones(3), np.ones(3), 0.1, unchanged=zero_correction(moved))
    assert fb.tolist() == [True, False, False] and "zero initial output" in why[0] and why[1:] == [None, None]
    fb, why = fallback_rule(np.ones(2), np.array([1.0, np.nan]), 0.1, unchanged=[True, True])
    assert "no validation" in why[1]  # without validation records the final network is taken, not the initial


def test_neural_config_checks():
    with pytest.raises(ValueError):
        NeuralConfig(val_fraction=1.0)
    with pytest.raises(ValueError):
        NeuralConfig(pretrain_epochs=0)
    assert NeuralConfig().n_synthetic_val == 400
