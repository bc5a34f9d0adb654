"""Hostile-input round 17: the fit core's public API (``fit``, its losses, priors and
batching strategies, the robust fit, change points, pooling, ``FitSolution``), the
predictive law, ``load_results`` and ``calibrate``'s options, as a Python user calls them.

Fit core: a string or a dict where ``fit`` takes a strategy, a loss, a prior or a solver
(``batching="vmap"``, ``loss="cauchy"``, ``prior={...}``, ``solver="lm"`` or a minimiser
such as ``optx.BFGS``) failed as an AttributeError inside the fit or optimistix, a fleet of
None or a path as "no attribute 'mask'", a model0 of a string as "empty model"; a free set
of no parameter as "integer modulo by zero" deep inside JAX. A Cauchy scale, a prior's
noise or a prior's centre for another number of heliostats failed in JAX's broadcasting
or the batching's scan; a prior of another model (an actuator model's prior for a Stone
fit) as an AttributeError. ``GaussianPrior`` built directly (or by ``fleet_prior`` /
``flat_prior`` from a NaN noise) took a sigma of 0 and a NaN noise, and every heliostat
came back DIVERGED without a word (a negative noise was taken too), though
``gaussian_prior`` refuses them; ``gaussian_prior`` of a string sigma failed in a
comparison and of a list of pairs called the pairs unknown parameters. ``Vmap(2.5)``
reached optimistix ("max_steps must be a Python integer"), ``Chunked(2.5)`` and
``Threaded(workers=2.5)`` failed inside JAX and NumPy; ``Threaded(inner=None)``,
``Sharded(devices="cpu")`` and ``Sharded(inner=Sharded())`` failed inside the fit, and
``Sharded(inner=Threaded())`` ran its blocks as a plain ``LaxMap`` without a word.

Robust fit and change points: ``fit_robust(passes=2.5)``, ``-3`` or ``"2"`` ran one pass
without a word and ``pool="no"`` pooled; a mask of another shape or of floats met the
fleet's mask before ``fit``'s own check (a NumPy broadcasting or JAX dtype error), in
``find_change_points`` too, which also scanned for a change with ``min_segment`` 0 or -1
(no record on one side), read 2.5 as 2, found nothing with NaN or negative weights, and
failed in JAX on weights of another shape or a solution of another fleet.

Pooling and solutions: ``fleet_prior(learn_from=[0, 1, 2, 3])`` read the heliostat indices
as booleans (index 0 dropped, the others taken), ``learn_from`` of another length failed
in NumPy's indexing and a noise per heliostat of another length was taken (failing in
the next fit); ``flat_prior(model, 0)`` made a prior of no heliostat and of 2.5 failed in
NumPy. ``FitSolution.heliostat_model(-1)`` was the last heliostat, ``True`` a batch of
one, 99 and 1.5 IndexErrors of NumPy. ``CompiledFit``'s ``only=[0, 2, 1]`` was read as
booleans (heliostat 0 kept, the others refitted), ``only`` for another number of
heliostats failed as XLA's "a different enable_x64 mode"; ``fleet_beam_errors_mrad`` and
``fleet_residuals_mrad`` of models batched for another fleet failed in a vmap naming
JAX's argument names, of a mask of another shape in NumPy's broadcasting, as did
``noise_outliers`` of arrays of two lengths.

Predictive law: ``PointingErrorLaw(tail_dof=None)`` failed in ``float()`` naming no field,
``True`` was one degree of freedom and the string "inf" was read; ``prediction_region_d2``
of "0.95" or of an array failed in a comparison, and a mixture's region at a probability of
1e-300 divided by zero. ``fit_drift_and_law`` (and the others) of no residual returned a
drift of 0 and a Gaussian law, and a scale that is no covariance (negative, zero,
asymmetric) gave a Student t law with NumPy's warnings.

Results and workflow: ``load_results(None)``, ``(0)`` and ``([path])`` called the file
damaged ("HDF5 cannot read it (TypeError: ...)") and ``load_results("")`` "not a
readable results.h5"; ``write_summary`` and ``write_results_h5`` of None or 0 failed as a
TypeError of pathlib naming nothing, of "" as "Is a directory: '.'". ``calibrate`` with
``n_train`` or ``n_val`` NaN or inf failed in ``int()`` (ValueError, OverflowError), a
string ``train_fraction`` in a comparison, an array of them as "truth value ...
ambiguous", ``n_train=True`` trained on one record; a
``seed`` of -1, 2.5, "42" or 2**40 reached scikit-learn, which named its ``random_state``;
a fleet of None or a ``test_fleet`` of a path failed as an AttributeError, a ``model`` of
None or 3 inside the fit.

The CLI's ``--config`` files were tried too (wrong types, nested tables, arrays for
scalars, huge values, a config named as an output of every command, through a link): all
were refused by key already.

Left by the round and then fixed: ``Cauchy("2")`` was read as 2.0 (failing inside the
fit); ``temporal_drift`` took ``min_records=0`` and held-out shares of 1.5 or NaN;
``CalibrationResults.fitted_records(inliers="no")`` was taken for True.

Ill-typed values are given under the ``unchecked`` fixture.
"""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import heliojax as hj
from heliojax import fitting
from heliojax._errors import ConfigError

MODEL = hj.StoneModel.nominal()


@pytest.fixture(scope="module")
def fleet():
    """3 heliostats x 8 records of synthetic arrays (nothing here is fitted)."""
    k = jax.random.split(jax.random.PRNGKey(17), 2)
    geometry = hj.synthetic_geometry(k[0], 3)
    context = hj.synthetic_contexts(k[1], 3, 8)
    return hj.fleet_from_arrays(geometry, jnp.full((3, 8, 2), 3e4), context, jnp.zeros((3, 8, 3)))


@pytest.fixture(scope="module")
def solution(fleet):
    """A solution of ``fleet``'s shapes (start models, zeros): no fit is run."""
    return hj.FitSolution.placeholder(MODEL, fleet)


# --------------------------------------------------------------------------------------
# the fit core
# --------------------------------------------------------------------------------------


def test_fit_names_a_strategy_loss_prior_or_solver_of_another_kind(fleet, unchecked):
    """A string or a dict had failed as an AttributeError inside the fit, a minimiser
    (BFGS) inside optimistix."""
    for name, value, said in (
        ("batching", "vmap", "fit: batching: expected e.g. heliojax.LaxMap()"),
        ("loss", "cauchy", r"fit: loss: expected heliojax.fitting.LeastSquares\(\) or"),
        ("prior", {"gamma": 1e-3}, r"fit: prior: expected heliojax.gaussian_prior"),
        ("solver", "lm", "fit: solver: expected an optimistix least-squares solver"),
        ("solver", optx.BFGS(1e-6, 1e-6), "fit: solver: .* got BFGS"),
    ):
        with pytest.raises(TypeError, match=f"^{said}"):
            hj.fit(MODEL, fleet, **{name: value})


def test_fit_and_calibrate_name_a_fleet_or_model_of_another_kind(fleet, unchecked):
    """A fleet of None (or a path) had been "'NoneType' object has no attribute 'mask'",
    a model0 of a string "empty model"; calibrate's ``model`` of None or 3 failed inside
    the fit and a ``test_fleet`` of a path as an AttributeError."""
    with pytest.raises(TypeError, match="^fit: fleet: expected a heliojax.Fleet .* got NoneType"):
        hj.fit(MODEL, None)
    with pytest.raises(TypeError, match="^fit: model0: expected a kinematic model .* got str"):
        hj.fit("stone8", fleet)
    with pytest.raises(TypeError, match="^calibrate: fleet: expected a heliojax.Fleet .* got str"):
        hj.calibrate("../shared/data/paint")
    with pytest.raises(TypeError, match="^calibrate: test_fleet: expected a heliojax.Fleet .* got str"):
        hj.calibrate(fleet, test_fleet="test/")
    for model in (None, 3):
        with pytest.raises(ConfigError, match=f"model must be 'auto', 'stone8', 'actuator' or a .* not {model}"):
            hj.calibrate(fleet, model=model)


def test_fit_refuses_a_free_set_of_no_parameter(fleet):
    """``free=no_free(model)`` had failed as "integer modulo by zero" inside JAX."""
    with pytest.raises(ValueError, match=r"^fit: free: no parameter is free"):
        hj.fit(MODEL, fleet, free=hj.no_free(MODEL))


def test_per_heliostat_scales_noises_and_centres_for_another_fleet_size_are_named(fleet):
    """For 3 heliostats, a Cauchy scale or a prior noise of 4 values had failed in JAX's
    broadcasting ("Incompatible types"), a centre batched over 4 in the batching's scan."""
    prior = hj.gaussian_prior(MODEL, {"gamma": 1e-3})
    with pytest.raises(ValueError, match=r"^Cauchy: scale_mrad has 4 values \(one per heliostat\); the fleet has 3"):
        hj.fit(MODEL, fleet, loss=fitting.Cauchy(jnp.ones(4)))
    four = hj.GaussianPrior(prior.centre, prior.sigma, jnp.ones(4))
    with pytest.raises(ValueError, match=r"^GaussianPrior: noise_mrad has 4 values .* the fleet has 3 heliostats"):
        hj.fit(MODEL, fleet, prior=four)
    batched = hj.GaussianPrior(hj.broadcast_model(MODEL, 4), prior.sigma, jnp.asarray(0.5))
    with pytest.raises(ValueError, match="^GaussianPrior: centre is batched over 4 heliostats; the fleet has 3"):
        hj.fit(MODEL, fleet, prior=batched)


def test_a_gaussian_prior_keeps_gaussian_priors_rules_however_it_is_built():
    """A sigma of 0 or a NaN noise had made every heliostat DIVERGED without a word, a
    negative noise was taken; ``fleet_prior`` and ``flat_prior`` of a NaN noise built them."""
    prior = hj.gaussian_prior(MODEL, {"gamma": 1e-3})
    zero = hj.ParameterView.of(MODEL).from_vector(MODEL, jnp.zeros(8))
    with pytest.raises(ValueError, match=r"^GaussianPrior: sigma must be > 0 \(inf: no prior .*\), got 0.0"):
        hj.GaussianPrior(MODEL, zero, jnp.asarray(0.5))
    for noise in (np.nan, -1.0, 0.0):
        with pytest.raises(
            ValueError, match=rf"^GaussianPrior: noise_mrad must be finite and > 0 \(mrad\), got {noise}"
        ):
            hj.GaussianPrior(prior.centre, prior.sigma, jnp.asarray(noise))
    with pytest.raises(ValueError, match="^GaussianPrior: noise_mrad must be finite"):
        fitting.flat_prior(MODEL, 2, float("nan"))
    # under jit the values are tracers: not checked (nor failed on)
    out = jax.jit(lambda n: hj.GaussianPrior(prior.centre, prior.sigma, n).noise_mrad)(jnp.asarray(-1.0))
    assert float(out) == -1.0


def test_a_prior_of_another_model_is_named(fleet):
    """An actuator model's prior for a Stone fit failed as "'ActuatorModel' object has no
    attribute 'theta_k'" inside the fit."""
    prior = hj.gaussian_prior(hj.ActuatorModel.nominal(), {"alpha": 1e-3})
    with pytest.raises(ValueError, match=r"^fit: prior: its centre is a ActuatorModel .* model0 \(StoneModel\) has"):
        hj.fit(MODEL, fleet, prior=prior)


def test_gaussian_prior_names_sigmas_that_are_no_mapping_of_numbers(unchecked):
    """A string sigma had failed in a comparison ("'>' not supported"), a list of pairs
    was "prior on unknown parameters [('gamma', 0.001)]"."""
    with pytest.raises(TypeError, match=r"^gaussian_prior: sigma\['gamma'\] must be a number, got '1e-3'"):
        hj.gaussian_prior(MODEL, {"gamma": "1e-3"})
    with pytest.raises(TypeError, match="^gaussian_prior: sigma must map parameter name -> sigma, not a list"):
        hj.gaussian_prior(MODEL, [("gamma", 1e-3)])
    assert hj.gaussian_prior(MODEL, {"gamma": np.float32(1e-3)}).noise_mrad == 0.5


def test_batching_counts_that_are_no_whole_numbers_are_named(unchecked):
    """``Vmap(2.5)`` had reached optimistix, ``"3"`` a comparison, ``Chunked(2.5)`` and
    ``Threaded(workers=2.5)`` failed inside JAX and NumPy."""
    for make, said in (
        (lambda: fitting.Vmap(restart_after=2.5), r"Vmap: restart_after must be a whole number, got 2.5"),
        (lambda: fitting.Vmap(restart_after="3"), r"Vmap: restart_after must be a whole number, got '3'"),
        (lambda: fitting.Chunked(2.5), r"Chunked: size must be a whole number, got 2.5"),
        (lambda: fitting.Threaded(workers=2.5), r"Threaded: workers must be a whole number, got 2.5"),
        (lambda: fitting.Threaded(min_block=0), r"Threaded: min_block must be at least 1, got 0"),
    ):
        with pytest.raises(ValueError, match=f"^{said}"):
            make()
    assert fitting.Vmap(restart_after=3).restart_after == 3 and fitting.Chunked(8).size == 8


def test_batching_inner_strategies_and_devices_of_another_kind_are_named(unchecked):
    """``Threaded(inner=None)`` and ``Sharded(devices="cpu")`` had been AttributeErrors
    inside the fit, ``Sharded(inner=Sharded())`` an IndexError; ``Sharded(inner=
    Threaded())`` ran as a plain LaxMap without a word."""
    with pytest.raises(TypeError, match=r"^Threaded: inner must be a batching strategy \(e.g. LaxMap\(\)\), got None"):
        fitting.Threaded(inner=None)
    with pytest.raises(TypeError, match="^Sharded: devices must be JAX devices .* got 'cpu'"):
        fitting.Sharded(devices="cpu")
    with pytest.raises(TypeError, match="^Sharded: inner must be a batching strategy .* got 'vmap'"):
        fitting.Sharded(inner="vmap")
    for inner in (fitting.Sharded(), fitting.Threaded()):
        with pytest.raises(
            ValueError, match=f"^Sharded: inner must batch one device's heliostats, got {type(inner).__name__}"
        ):
            fitting.Sharded(inner=inner)
    assert fitting.Sharded(devices=tuple(jax.local_devices()), inner=fitting.LaxMap()).inner == fitting.LaxMap()


# --------------------------------------------------------------------------------------
# robust fit, change points, pooling, solutions
# --------------------------------------------------------------------------------------


def test_fit_robust_refuses_passes_and_pool_it_would_misread(fleet, unchecked):
    """``passes`` of 2.5, -3 or "2" had run one pass without a word, ``pool="no"`` pooled."""
    for passes, said in (
        (2.5, "must be a whole number, got 2.5"),
        (-3, "must be at least 1, got -3"),
        ("2", "must be a whole number, got '2'"),
    ):
        with pytest.raises(ValueError, match=f"^fit_robust: passes {said}"):
            fitting.fit_robust(MODEL, fleet, passes=passes)
    with pytest.raises(TypeError, match="^fit_robust: pool must be True or False, got 'no'"):
        fitting.fit_robust(MODEL, fleet, pool="no")


def test_robust_fit_and_change_points_check_the_mask_before_using_it(fleet, solution, unchecked):
    """A mask of another shape met the fleet's mask in NumPy's broadcasting, a float mask
    failed in JAX's ``&``: ``fit``'s own check came after."""
    weights = np.ones((3, 8))
    for mask, said in (
        (np.ones((3, 5), bool), r"mask has shape \(3, 5\); expected \(3, 8\)"),
        (np.ones((3, 8)), "mask has dtype float64"),
    ):
        with pytest.raises(ValueError, match=f"^fit_robust: {said}"):
            fitting.fit_robust(MODEL, fleet, mask=mask)
        with pytest.raises(ValueError, match=f"^find_change_points: {said}"):
            fitting.find_change_points(solution, fleet, mask, weights)


def test_change_points_name_a_segment_weights_or_solution_they_would_misread(fleet, solution, unchecked):
    """``min_segment`` 0 or -1 scanned for changes with no record on one side, 2.5 was
    read as 2; NaN or negative weights found nothing without a word; weights of another
    shape and a solution of another fleet failed inside JAX."""
    mask, weights = np.asarray(fleet.mask), np.ones((3, 8))
    for segment, said in (
        (0, "must be at least 1, got 0"),
        (-1, "must be at least 1, got -1"),
        (2.5, "must be a whole number, got 2.5"),
    ):
        with pytest.raises(ValueError, match=f"^find_change_points: min_segment {said}"):
            fitting.find_change_points(solution, fleet, mask, weights, min_segment=segment)
    for bad in (np.full((3, 8), np.nan), -weights):
        with pytest.raises(ValueError, match="^find_change_points: weights must be finite and >= 0"):
            fitting.find_change_points(solution, fleet, mask, bad)
    with pytest.raises(ValueError, match=r"^find_change_points: weights has shape \(3, 5\); expected \(3, 8\)"):
        fitting.find_change_points(solution, fleet, mask, np.ones((3, 5)))
    other = hj.fleet_subset(fleet, [0, 1])
    with pytest.raises(ValueError, match="^find_change_points: solution holds 3 heliostats and the fleet 2"):
        fitting.find_change_points(solution, other, np.asarray(other.mask), np.ones((2, 8)))


def test_fleet_and_flat_priors_name_indices_lengths_and_counts(solution, unchecked):
    """``learn_from=[0, 1, 2]`` had been read as booleans (heliostat 0 left out, the
    others taken), 2 booleans for 3 failed in NumPy's indexing, a noise for 2 heliostats
    was taken; ``flat_prior(model, 0)`` made a prior of no heliostat, of 2.5 a NumPy error."""
    noise = jnp.full(3, 0.2)
    for learn_from in (np.array([0, 1, 2]), np.ones(2, bool)):
        with pytest.raises(ValueError, match=r"^fleet_prior: learn_from must be \(3,\) booleans, one per heliostat"):
            fitting.fleet_prior(solution, noise, learn_from=learn_from)
    with pytest.raises(ValueError, match=r"^fleet_prior: noise_mrad has shape \(2,\); expected \(\) or \(3,\)"):
        fitting.fleet_prior(solution, jnp.full(2, 0.2))
    for n, said in ((0, "must be at least 1, got 0"), (2.5, "must be a whole number, got 2.5")):
        with pytest.raises(ValueError, match=f"^flat_prior: n {said}"):
            fitting.flat_prior(MODEL, n)


def test_heliostat_model_names_an_index_outside_the_fleet(solution, unchecked):
    """-1 had been the last heliostat, True a batch of one heliostat, 99 and 1.5
    IndexErrors of NumPy."""
    for i, said in (
        (-1, "at least 0, got -1"),
        (99, "at most 2, got 99"),
        (True, "a whole number, got True"),
        (1.5, "a whole number, got 1.5"),
    ):
        with pytest.raises(ValueError, match=f"^heliostat_model: i must be {said}"):
            solution.heliostat_model(i)
    assert jnp.shape(solution.heliostat_model(jnp.argmax(jnp.arange(3))).alpha) == ()


def test_compiled_fit_names_heliostats_to_refit_given_as_indices_or_for_another_fleet(fleet, unchecked):
    """``only=[0, 2, 1]`` had been read as booleans (heliostat 0 kept, 1 and 2 refitted),
    ``only`` of 2 for 3 heliostats failed as XLA's "Argument types differ ... a different
    enable_x64 mode", an ``otherwise`` of another kind in a tree_map."""
    run = fitting.CompiledFit(MODEL, fleet, max_steps=1, batching=fitting.LaxMap())
    first = run(MODEL)
    for only in (np.array([0, 2, 1]), np.ones(2, bool)):
        with pytest.raises(ValueError, match=r"^CompiledFit: only must be \(3,\) booleans, one per heliostat"):
            run(MODEL, only=only, otherwise=first)
    with pytest.raises(TypeError, match="^CompiledFit: otherwise must be a FitSolution of the fleet, got str"):
        run(MODEL, only=np.ones(3, bool), otherwise="first")
    assert run(MODEL, only=np.array([True, False, True]), otherwise=first).n_heliostats == 3


def test_fleet_evaluations_name_models_or_masks_for_another_fleet(fleet, unchecked):
    """Models batched over 4 heliostats for a fleet of 3 had failed in a vmap naming JAX's
    argument names (``model.alpha``), a mask of another shape in NumPy's broadcasting."""
    with pytest.raises(
        ValueError, match="^fleet_beam_errors_mrad: models is batched over 4 heliostats and the fleet has 3"
    ):
        fitting.fleet_beam_errors_mrad(hj.broadcast_model(MODEL, 4), fleet)
    with pytest.raises(ValueError, match=r"^fleet_residuals_mrad: mask has shape \(3, 5\); expected \(3, 8\)"):
        fitting.fleet_residuals_mrad(MODEL, fleet, np.ones((3, 5), bool))
    with pytest.raises(ValueError, match=r"^noise_outliers: own has shape \(4,\) and candidates \(3,\)"):
        fitting.noise_outliers(np.ones(4), np.ones(3, bool))


# --------------------------------------------------------------------------------------
# predictive law, results, workflow
# --------------------------------------------------------------------------------------


def test_pointing_error_law_fields_and_probabilities_that_are_no_numbers_are_named(unchecked):
    """``tail_dof=None`` had failed in ``float()`` naming no field, ``True`` was one
    degree of freedom, "inf" was read; a probability of "0.95" or an array failed in a
    comparison; a mixture's region at p = 1e-300 divided by zero."""
    for value in (None, True, "inf", np.array([3.0, 4.0])):
        with pytest.raises(TypeError, match="^PointingErrorLaw: tail_dof, outlier_fraction and outlier_scale must be"):
            hj.PointingErrorLaw(tail_dof=value)
    for p in ("0.95", np.array([0.5, 0.9])):
        with pytest.raises(ValueError, match=r"^probability must be in \(0, 1\); got"):
            hj.prediction_region_d2(p)
    mixture = hj.PointingErrorLaw(outlier_fraction=0.5, outlier_scale=1000.0)
    assert 0.0 < mixture.region_d2(1e-300) < 1e-290
    assert hj.PointingErrorLaw(tail_dof=np.float32(4.0)).tail_dof == 4.0


def test_drift_and_law_fits_refuse_no_residual_and_scales_that_are_no_covariance():
    """No residual had given a drift of 0 and a Gaussian law; a negative, zero or
    asymmetric scale a Student t law (with NumPy's warnings of log and sqrt)."""
    r = np.random.default_rng(17).normal(size=(6, 2))
    s, days = np.tile(np.eye(2), (6, 1, 1)), np.arange(6.0)
    for call in (hj.fit_drift_and_law, hj.fit_drift_and_tails, hj.fit_drift_terms_and_law):
        with pytest.raises(ValueError, match="^residual_mrad: no residual"):
            call(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0))
    for bad in (-s, 0.0 * s, s + np.array([[0.0, 5.0], [0.0, 0.0]])):
        with pytest.raises(ValueError, match=r"^scale_mrad2: 6 matrix\(es\) not symmetric positive definite"):
            hj.fit_drift_and_law(r, bad, days)
    assert hj.fit_drift_and_law(r, s, days)[0] >= 0.0


def test_load_results_of_no_path_is_named_not_called_damaged(unchecked):
    """None, 0 and a list had been "damaged: HDF5 cannot read it (TypeError: ...)", ""
    "not a readable results.h5 (invalid file name)"."""
    for value in (None, 0, ["results.h5"]):
        with pytest.raises(TypeError, match=r"^path: expected a file or folder path \(str or os.PathLike\)"):
            hj.load_results(value)
    with pytest.raises(ValueError, match="^path: empty path"):
        hj.load_results("")


def test_results_and_summary_writers_name_a_path_that_is_no_path(tmp_path, monkeypatch, unchecked):
    """``write_summary(None, run)`` (or 0, bytes) had failed as a TypeError of pathlib
    naming nothing, ``write_summary("", run)`` as "Is a directory: '.'"; so had
    ``write_results_h5``."""
    monkeypatch.chdir(tmp_path)
    run = types.SimpleNamespace(summary={"heliostats": {}})
    for write in (hj.write_summary, hj.write_results_h5):
        for value in (None, 0, b"summary.json"):
            with pytest.raises(TypeError, match="^path: expected"):
                write(value, run)
        with pytest.raises(ValueError, match="^path: empty path"):
            write("", run)
    assert list(tmp_path.iterdir()) == []
    hj.write_summary("summary.json", run)
    assert (tmp_path / "summary.json").read_text() == '{\n  "heliostats": {}\n}\n'


@pytest.mark.parametrize(
    ("options", "said"),
    [
        ({"n_train": float("nan")}, "n_train must be a positive integer, got nan"),
        ({"n_train": float("inf")}, "n_train must be a positive integer, got inf"),
        ({"n_train": True}, "n_train must be a positive integer, got True"),
        ({"n_val": float("nan")}, "n_val must be a non-negative integer, got nan"),
        ({"train_fraction": "0.5"}, r"train_fraction must lie in \(0, 1\), got '0.5'"),
        ({"train_fraction": np.array([0.5, 0.6])}, r"train_fraction must lie in \(0, 1\), got array"),
    ],
    ids=["n_train-nan", "n_train-inf", "n_train-true", "n_val-nan", "fraction-string", "fraction-array"],
)
def test_calibrate_names_split_sizes_that_are_no_numbers(fleet, options, said, unchecked):
    """NaN and inf had failed in ``int()`` (ValueError, OverflowError), a string fraction
    in a comparison, an array as "truth value ... ambiguous"; True trained on one record."""
    with pytest.raises(ConfigError, match=f"^{said}"):
        hj.calibrate(fleet, **options)


def test_calibrate_names_a_seed_scikit_learn_would_refuse(fleet, unchecked):
    """-1, 2.5, "42" and 2**40 had reached scikit-learn's KMeans, which named its own
    ``random_state``."""
    for seed in (-1, 2.5, "42", 2**40):
        with pytest.raises(ConfigError, match=r"^seed must be a whole number in \[0, 4294967295\] \(or None\)"):
            hj.calibrate(fleet, split="balanced", n_train=4, n_val=2, seed=seed)


def test_what_round_17_left_is_refused(unchecked):
    """Left by the round, then fixed: ``Cauchy("2")`` was read as 2.0 and failed inside
    the fit; ``temporal_drift`` took ``min_records=0`` and shares of 1.5 or NaN;
    ``fitted_records(inliers="no")`` was taken for True."""
    with pytest.raises(TypeError, match="Cauchy: scale_mrad must be a number"):
        fitting.Cauchy("2")  # pyright: ignore[reportArgumentType]
    fleet = hj.load_paint_directory(hj.default_data_dir())
    train = np.asarray(fleet.mask)
    for options, match in (
        ({"min_records": 0}, "min_records must be at least 2"),
        ({"min_records": 2.5}, "min_records must be a whole number"),
        ({"fractions": [1.5]}, "fractions must be shares in"),
        ({"fractions": [float("nan")]}, "fractions must be shares in"),
        ({"fractions": []}, "fractions must be shares in"),
    ):
        with pytest.raises(ConfigError, match=match):
            hj.temporal_drift(None, fleet, train, **options)  # pyright: ignore[reportArgumentType]


def test_fitted_records_takes_a_bool_only(fitted_h5, unchecked):
    results = hj.load_results(fitted_h5)
    with pytest.raises(TypeError, match="inliers must be True or False"):
        results.fitted_records(inliers="no")  # pyright: ignore[reportArgumentType]
    assert results.fitted_records(inliers=True).sum() <= results.fitted_records(inliers=False).sum()
