"""Hostile-input round 13: problems found and left in earlier rounds, and the ARTIST
scenario reader and the neural correction's API.

Left from earlier rounds: ``set_references`` ignored a misspelled name; an actuator
increment of 0 (or an offset, pivot radius of 0) divided the counts by zero; a Cauchy
scale of 0 or NaN made a heliostat's rows NaN; ``simulate_records(noise_mrad=nan)``
masked every record without a word; synthetic fleets of absurd sizes were refused
only by XLA running out of memory; an image grid of negative, zero or NaN width drew
a mirrored or NaN image; ``HeliostatGeometry.build`` of arguments for different
numbers of heliostats failed in ``broadcast_to`` (or, for the actuators, not at all);
``calibrate(fit_options={"mask": ...})`` failed with Python's "got multiple values".

ARTIST scenarios: a group where a dataset belongs, text not UTF-8, a flag of "yes", a
NURBS degree of 2.7, motor limits reversed or past 32 bits, an increment of 0, a
repeated id, a negative ray count, a target of negative width or no normal, a plant
past the pole, a heliostat a million kilometres off, a dangling or looping link: each
had been a TypeError, ValueError, IndexError or RuntimeError from h5py or NumPy, or
was read without a word; each is now a :class:`~heliojax.DataError` naming the file
and the HDF5 path.

Neural correction: networks of mismatched layers failed at their first call inside
``dot_general``; a layer width of 2.7 was cut to 2; a NaN fallback tolerance let every
network through; ``fallback_rule`` of lists of different lengths dropped heliostats;
``calibrate_neural`` with a dict for ``nn`` failed with an AttributeError, and with an
``lm_run`` of other heliostats ignored its ``fleet``; a learning curve of size 0
trained on every record.

Ill-typed values are given under the ``unchecked`` fixture (the test run's jaxtyping
checker would refuse them first; a user has none)."""

from __future__ import annotations

import dataclasses
import shutil

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHARED_PAINT

import heliojax as hj
from heliojax import neural, optics
from heliojax._errors import ConfigError, DataError
from heliojax._simulate import calibration_times, typical_actuators
from heliojax.paint import read_artist_scenario

SCENARIO = SHARED_PAINT.parent / "artist-scenarios" / "paint_four_heliostats_deflectometry.h5"


# --------------------------------------------------------------------------------------
# Part A: left from earlier rounds
# --------------------------------------------------------------------------------------


def test_set_references_names_an_unknown_reference_and_the_known_ones():
    model = hj.with_effects(hj.StoneModel.nominal(), "thermal")
    with pytest.raises(ValueError, match=r"unknown reference\(s\) 'thermal_ref_c'.*thermal_reference_c"):
        hj.set_references(model, {"thermal_ref_c": 12.0})
    with pytest.raises(ValueError, match=r"references are: none"):
        hj.set_references(hj.StoneModel.nominal(), {"thermal_reference_c": 12.0})
    with pytest.raises(ValueError, match=r"thermal_reference_c must be a finite real number, got nan"):
        hj.set_references(model, {"thermal_reference_c": float("nan")})
    set_ = hj.set_references(model, {"thermal_reference_c": 12.0})
    assert float(set_.effects[0].reference) == 12.0


def test_actuators_refuse_an_increment_offset_or_pivot_of_zero_where_known():
    act = typical_actuators()
    with pytest.raises(ValueError, match=r"increment must be finite and > 0 \(counts per metre\), got 0.0 at axis 1"):
        dataclasses.replace(act, increment=jnp.asarray([0.0, 1.5e5]))
    batched = typical_actuators(3)
    with pytest.raises(
        ValueError, match=r"pivot_radius must be finite and > 0 \(m\), got nan at axis 2 of heliostat 1"
    ):
        dataclasses.replace(batched, pivot_radius=batched.pivot_radius.at[1, 1].set(jnp.nan))
    with pytest.raises(ValueError, match=r"offset must be finite and > 0"):
        dataclasses.replace(act, offset=-act.offset)
    # under jit the values are tracers: not checked (nor failed on)
    out = jax.jit(lambda x: dataclasses.replace(act, increment=x).increment)(jnp.zeros(2))
    assert out.shape == (2,)


def test_cauchy_refuses_a_scale_of_zero_or_nan_and_keeps_inf_for_least_squares():
    with pytest.raises(ValueError, match=r"Cauchy: scale_mrad must be > 0 .*got 0.0"):
        hj.fitting.Cauchy(jnp.asarray(0.0))
    with pytest.raises(ValueError, match=r"got nan \(heliostat 1\)"):
        hj.fitting.Cauchy(jnp.asarray([1.0, jnp.nan]))
    assert hj.fitting.Cauchy(jnp.asarray([2.0, jnp.inf])).scale_mrad.shape == (2,)


@pytest.mark.parametrize(("name", "value"), [("noise_mrad", float("nan")), ("noise_mrad", -0.1), ("noise_m", np.inf)])
def test_simulate_records_refuses_a_noise_that_is_not_finite_and_non_negative(name, value, unchecked):
    geometry = hj.synthetic_geometry(jax.random.key(0), 2)
    with pytest.raises(ValueError, match=rf"simulate_records: {name} must be a finite number >= 0, got"):
        hj.simulate_records(jax.random.key(1), None, geometry, None, None, **{name: value})


def test_synthetic_fleets_of_absurd_sizes_are_refused_before_allocation(unchecked):
    key = jax.random.key(0)
    with pytest.raises(ValueError, match=r"synthetic_geometry: n must be at most 1,000,000, got 1,000,000,000,000"):
        hj.synthetic_geometry(key, 10**12)
    with pytest.raises(ValueError, match=r"random_stone_models: n must be at least 1, got -3"):
        hj.random_stone_models(key, -3)
    with pytest.raises(ValueError, match=r"synthetic_contexts: n_heliostats x n_records = 100,000,000 records"):
        hj.synthetic_contexts(key, 10_000, 10_000)
    with pytest.raises(ValueError, match=r"synthetic_contexts: n_records must be a whole number, got 2.5"):
        hj.synthetic_contexts(key, 2, 2.5)
    with pytest.raises(ValueError, match=r"calibration_times: shape\[0\] must be at most 10,000,000"):
        calibration_times(key, (10**9,))
    with pytest.raises(ValueError, match=r"typical_actuators: n must be at most"):
        typical_actuators(10**9)


@pytest.mark.parametrize(
    ("edges", "said"),
    [
        ((0.5, -0.5, 0.0, 1.0), r"u_min < u_max, both finite \(m\), needed; got u_min = 0.5, u_max = -0.5"),
        ((0.0, 1.0, 1.0, 1.0), r"v_min < v_max.*got v_min = 1.0, v_max = 1.0"),
        ((0.0, np.nan, 0.0, 1.0), r"u_min < u_max.*u_max = nan"),
        ((-np.inf, 1.0, 0.0, 1.0), r"u_min = -inf"),
    ],
)
def test_image_grid_refuses_a_negative_zero_or_non_finite_extent(edges, said):
    u0, u1, v0, v1 = (jnp.asarray(e) for e in edges)
    with pytest.raises(ValueError, match=said):
        optics.ImageGrid(u_min=u0, u_max=u1, v_min=v0, v_max=v1, shape=(4, 4))
    with pytest.raises(ValueError, match=r"ImageGrid: u_min < u_max"):
        optics.ImageGrid.centred(0.0, 0.0, -1.0, 1.0, (4, 4))


def test_geometry_build_names_arguments_for_other_heliostats(unchecked):
    position = jnp.zeros((5, 3))
    with pytest.raises(
        ValueError, match=r"build: actuators has shape \(4, 2\), but position \(5, 3\) holds heliostats"
    ):
        hj.HeliostatGeometry.build(position, typical_actuators(4))
    with pytest.raises(ValueError, match=r"concentrator_translation has shape \(4, 3\).*expected \(5, 3\) or \(3,\)"):
        hj.HeliostatGeometry.build(position, typical_actuators(5), concentrator_translation=jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"ideal_axes has shape \(3,\)"):
        hj.HeliostatGeometry.build(position, typical_actuators(5), ideal_axes=(True, False, True))
    with pytest.raises(ValueError, match=r"position has shape \(2,\); expected \(\.\.\., 3\)"):
        hj.HeliostatGeometry.build(jnp.zeros(2), typical_actuators())
    # one translation for all heliostats still broadcasts
    g = hj.HeliostatGeometry.build(position, typical_actuators(5), concentrator_translation=(0.0, 0.175, 0.0))
    assert g.concentrator_translation.shape == (5, 3)


@pytest.mark.parametrize(
    ("options", "kw", "said"),
    [
        ({"mask": None}, {}, r"fit_options: 'mask' is set by calibrate itself: .*record_roles"),
        ({"loss": None}, {}, r"'loss' is set by calibrate itself: robust=True"),
        ({"prior": None}, {}, r"'prior' is set by calibrate itself: robust=True with pool=True"),
        ({"max_step": 3}, {}, r"unknown key\(s\) 'max_step'; known: free, solver, loss, prior, batching, max_steps"),
        ([("max_steps", 3)], {}, r"fit_options must map keyword -> value, not a list"),
    ],
)
def test_calibrate_names_fit_options_it_sets_itself_or_does_not_know(options, kw, said, unchecked):
    with pytest.raises(ConfigError, match=said):
        hj.calibrate(None, fit_options=options, **kw)


# --------------------------------------------------------------------------------------
# Part B: ARTIST scenario files
# --------------------------------------------------------------------------------------

_H = "heliostats/AA39/"


def _replace(path, value):
    def edit(f):
        del f[path]
        f[path] = value

    return edit


def _make_group(path):
    def edit(f):
        del f[path]
        f.create_group(path)

    return edit


ARTIST_CASES = [
    ("group-for-text", _make_group(_H + "actuator/actuator_0/type"), _H + "actuator/actuator_0/type", "is a group"),
    ("text-not-utf8", _replace(_H + "actuator/actuator_0/type", np.bytes_(b"\xff\xfe")), "type", "not UTF-8"),
    (
        "flag-yes",
        _replace(_H + "actuator/actuator_0/clockwise_axis_movement", np.bytes_(b"yes")),
        "clockwise",
        "a boolean",
    ),
    ("flag-2", _replace(_H + "actuator/actuator_1/clockwise_axis_movement", np.int64(2)), "clockwise", "a boolean"),
    (
        "degree-2.7",
        _replace(_H + "surface/facets/facet_1/degrees", np.array([2.7, 2.7])),
        "degrees",
        "2.7; expected a whole",
    ),
    ("degree-0", _replace(_H + "surface/facets/facet_2/degrees", np.array([0, 0])), "degrees", "0; expected a whole"),
    (
        "limits-reversed",
        _replace(_H + "actuator/actuator_0/min_max_motor_positions", np.array([9, 0])),
        "min_max",
        "not below",
    ),
    (
        "limits-huge",
        _replace(_H + "actuator/actuator_0/min_max_motor_positions", np.array([0, 1e30])),
        "min_max",
        "1e\\+30",
    ),
    (
        "increment-0",
        _replace(_H + "actuator/actuator_0/parameters/increment", np.float32(0)),
        "increment",
        "expected > 0",
    ),
    (
        "pivot-negative",
        _replace(_H + "actuator/actuator_1/parameters/pivot_radius", np.float32(-1)),
        "pivot_radius",
        "> 0",
    ),
    ("id-1.5", _replace(_H + "id", np.float64(1.5)), _H + "id", "1.5; expected a whole"),
    ("id-repeated", _replace(_H + "id", np.int64(1)), _H + "id", "the id of heliostats/AA31 too"),
    ("rays-negative", _replace("lightsources/sun_1/number_of_rays", np.int64(-5)), "number_of_rays", "-5"),
    (
        "groups-text",
        _replace("number_of_heliostat_groups", np.bytes_(b"x")),
        "number_of_heliostat_groups",
        "not numeric",
    ),
    ("version-text", lambda f: f.attrs.__setitem__("version", "abc"), "version", "not a number"),
    ("heliostat-dataset", lambda f: f.__setitem__("heliostats/ZZ99", np.float64(1)), "heliostats/ZZ99", "is a dataset"),
    (
        "target-dataset",
        lambda f: f.__setitem__("target_areas_planar/x", np.float64(1)),
        "target_areas_planar/x",
        "dataset",
    ),
    ("target-width", _replace("target_areas_planar/multi_focus_tower/plane_e", np.float32(-5)), "plane_e", "-5 m"),
    (
        "target-normal",
        _replace("target_areas_planar/multi_focus_tower/normal_vector", np.zeros((0, 4))),
        "normal",
        "no dir",
    ),
    ("plant-past-pole", _replace("power_plant/position", np.array([200.0, 6.0, 87.0])), "power_plant", "latitude 200"),
    ("heliostat-far", _replace(_H + "position", np.array([1e9, 0.0, 0.0, 1.0])), _H + "position", "1e\\+09 m"),
    ("cylinder-group", lambda f: f["target_areas_cylindrical"].create_group("w/sub"), "cylindrical/w/sub", "a group"),
    (
        "link-loop",
        lambda f: f.__setitem__("heliostats/ZZ", h5py.SoftLink("/heliostats/ZZ")),
        "heliostats/ZZ",
        "cannot be",
    ),
    (
        "link-dangling",
        lambda f: f.__setitem__("heliostats/ZZ", h5py.ExternalLink("gone.h5", "/x")),
        "heliostats/ZZ",
        "cannot",
    ),
]


@pytest.mark.parametrize(("edit", "field", "said"), [c[1:] for c in ARTIST_CASES], ids=[c[0] for c in ARTIST_CASES])
def test_a_damaged_artist_scenario_is_named_by_file_and_field(edit, field, said, tmp_path, shared_paint):
    del shared_paint  # skips without the shared data
    path = tmp_path / "scenario.h5"
    shutil.copy(SCENARIO, path)
    with h5py.File(path, "r+") as f:
        edit(f)
    with pytest.raises(DataError, match=said) as e:
        read_artist_scenario(path)
    assert e.value.file == str(path) and e.value.field is not None and field in e.value.field, str(e.value)


def test_the_real_artist_scenarios_still_read(shared_paint):
    for name in ("paint_four_heliostats_deflectometry.h5", "paint_four_heliostats_ideal.h5"):
        scenario = read_artist_scenario(shared_paint.parent / "artist-scenarios" / name)
        assert [h.name for h in scenario.heliostats] == ["AA28", "AA31", "AA39", "AC43"]
        assert scenario.number_of_heliostat_groups == 2


def test_one_damaged_heliostat_of_a_scenario_spoils_only_itself(tmp_path, shared_paint, capsys):
    """A damaged heliostat group made the whole scenario unreadable, so `reconstruct
    --scenario` failed for every heliostat of the file. With ``skip_bad`` it is left
    out and named; `reconstruct` refuses only that heliostat, naming why."""
    from helpers import run_cli

    path = tmp_path / "scenario.h5"
    shutil.copy(SCENARIO, path)
    with h5py.File(path, "r+") as f:
        _replace(_H + "actuator/actuator_1/parameters/pivot_radius", np.float32(-1))(f)
    with pytest.raises(DataError, match="pivot_radius"):
        read_artist_scenario(path)
    scenario = read_artist_scenario(path, skip_bad=True)
    assert [h.name for h in scenario.heliostats] == ["AA28", "AA31", "AC43"]
    assert [name for name, _ in scenario.skipped] == ["AA39"] and "pivot_radius" in scenario.skipped[0][1]
    assert optics.scene_from_artist(path, skip_bad=True).heliostat_ids == ("AA28", "AA31", "AC43")
    root = tmp_path / "paint"
    shutil.copytree(shared_paint / "flux-samples" / "AA39", root / "AA39")
    shutil.copy(next(shared_paint.glob("*-tower-measurements.json")), root)
    argv = ["reconstruct", "--paint", str(root), "--heliostat", "AA39", "--scenario", str(path)]
    rc, _, err = run_cli([*argv, "--out", str(tmp_path / "out")], capsys)
    assert rc == 2 and "heliostat AA39 is damaged there" in err and "pivot_radius" in err, err


# --------------------------------------------------------------------------------------
# Part B: the neural correction's API
# --------------------------------------------------------------------------------------


def test_networks_of_mismatched_layers_or_widths_are_named(unchecked):
    with pytest.raises(ValueError, match=r"MLP: weights\[1\] takes 5 inputs but layer 0 gives 4"):
        neural.MLP(weights=(jnp.ones((4, 3)), jnp.ones((2, 5))), biases=(jnp.ones(4), jnp.ones(2)))
    with pytest.raises(ValueError, match=r"MLP: biases\[0\] has shape \(5,\); expected \(4,\)"):
        neural.MLP(weights=(jnp.ones((4, 3)),), biases=(jnp.ones(5),))
    key = jax.random.key(0)
    with pytest.raises(ValueError, match=r"MLP sizes must be >= 2 whole numbers in \[1, 4096\], got \(5, 2.7, 1\)"):
        neural.MLP.init(key, (5, 2.7, 1))
    with pytest.raises(ValueError, match=r"got \(5, True, 1\)"):
        neural.MLP.init(key, (5, True, 1))
    with pytest.raises(ValueError, match=r"MLP: input of shape \(4,\); the network takes \(5,\)"):
        neural.MLP.init(key, (5, 3, 1))(jnp.ones(4))
    with pytest.raises(ValueError, match=r"init_networks: shape must hold whole numbers >= 1, got \(-2,\)"):
        neural.init_networks(key, (-2,), (5, 3, 1))
    with pytest.raises(ValueError, match=r"n_synthetic must be at most 10,000,000"):
        neural.NeuralConfig(n_synthetic=10**12)
    with pytest.raises(ValueError, match=r"hidden\[0\] must be at most 4096"):
        neural.NeuralConfig(hidden=(10**9,))


def test_fallback_rule_and_validation_tail_refuse_what_they_would_misread():
    with pytest.raises(ValueError, match=r"tolerance must be a finite number >= 0, got nan"):
        neural.fallback_rule(np.array([5.0]), np.array([1.0]), float("nan"))
    with pytest.raises(ValueError, match=r"one value per heliostat needed"):
        neural.fallback_rule(np.array([1.0, 9.0]), np.array([1.0]), 0.1)
    fallback, _ = neural.fallback_rule(np.array([5.0, 1.0]), np.array([1.0, 1.0]), 0.1)
    assert fallback.tolist() == [True, False]
    with pytest.raises(ValueError, match=r"val_fraction must be a number in \[0, 1\), got nan"):
        neural.validation_tail(np.ones((2, 10), bool), float("nan"))
    with pytest.raises(ValueError, match=r"min_val must be a whole number >= 0, got -1"):
        neural.validation_tail(np.ones((2, 10), bool), 0.2, min_val=-1)


def test_calibrate_neural_and_learning_curve_name_bad_arguments(unchecked):
    with pytest.raises(ConfigError, match=r"nn must be a heliojax.neural.NeuralConfig, not a dict"):
        neural.calibrate_neural(None, nn={"val_fraction": 0.2})

    @dataclasses.dataclass
    class Run:
        summary: dict

    fleet = dataclasses.make_dataclass("F", ["ids"])(ids=("A", "B"))
    with pytest.raises(ConfigError, match=r"lm_run was fitted on other heliostats \(A, C\) than fleet's \(A, B\)"):
        neural.calibrate_neural(fleet, lm_run=Run({"heliostats": {"A": {}, "C": {}}}))
    with pytest.raises(ConfigError, match=r"sizes must be whole numbers >= 1, got \[0, 5\]"):
        neural.learning_curve(fleet, [0, 5])
    with pytest.raises(ConfigError, match=r"test_fraction must be a number in \(0, 1\), got nan"):
        neural.learning_curve(fleet, [5], test_fraction=float("nan"))
