"""Hostile-input round 18: what earlier rounds left open (effects built directly, discovery
of a fleet without a record, the fit's step budget, the robust noise's and the process
slice's counts), the model pytrees, the actuators, the geometry and the padded record
container built directly, the sun-position and direction helpers, the benchmark scripts'
command lines and their outputs when a run is interrupted.

Left open: an effect built directly (``Backlash(width=[nan, 0], ...)``,
``GravitySag(inf)``, ``Clock(offset=nan, ...)``) took NaN and inf, and every prediction
of it was NaN; only ``make_effect`` checked. ``discover`` of a fleet whose every record
is masked (a PAINT folder whose calibration files are all unreadable) compiled and ran
for ~20 s, then failed inside NumPy ("cannot reshape array of size 0 into shape (0)"),
in the library and as ``heliojax discover``'s traceback. ``fit(max_steps=2**40)`` was
taken and ``calibrate --max-steps`` took up to 2**31 - 1 (discovery took 100,000).
``robust_noise`` and ``robust_component_noise`` took ``n_free=-1`` (raising every
heliostat's degrees of freedom) and 2.5; ``process_slice`` read 2.5 heliostats as 2
and ``True`` as 1.

Model pytrees built directly: ``StoneModel(alpha=0.0, ..., gr1=1.0, gr2=1.0)``, the
natural notebook spelling, failed in ``fit`` as "'float' object has no attribute
'shape'" (Python floats were kept as they are; they now become arrays). A string
parameter was taken and failed at the model's first use ("asarray: expected ArrayLike"),
None inside the fit, ``True`` was 1 rad; a NaN or inf parameter made every pose NaN
without a word, a gear ratio of 0 divided by zero (NaN poses), an ``increment_scale``
of -1 made the actuator's increment 0 (finite, wrong angles from a clipped law of
cosines); ``ActuatorModel(angle_offset=0.0)`` or of three values, and a ``StoneModel``
whose ``alpha`` alone had a heliostat axis, failed inside the fit (an AttributeError,
"scan got value with no leading axis").

``LinearActuators`` built directly took a ``sign`` of 0 (a joint that never turns) and
NaN or inf angles and count ranges (only the three lengths it divides by were checked);
``HeliostatGeometry.build`` read ``ideal_axes=("no", "no")`` as two ideal axes and 0.5
as True, took a NaN position (every pose NaN) and failed on a position given as text
inside JAX.

The record container: ``Fleet`` built directly with a float mask failed in JAX's ``and``
inside the fit, with a mask of one axis as "not enough values to unpack"; it took ids
that are no strings and an id twice. ``fleet_from_arrays`` of counts without the record
axis, of focal spots or contexts of another record count failed in JAX's or NumPy's
broadcasting naming no argument, of a geometry or context of None as an
AttributeError; it took the id ``""`` (which marks a padding heliostat: that heliostat
was left out of every statistic), ``"a,b"`` and integers. ``pad_fleet`` read 8.5 as 8,
``True`` as 1 and ``"16"`` as 16 (10**12 was a MemoryError of NumPy); ``Fleet.heliostat``
read ``True`` as heliostat 1 and 1.7 as 1.

Sun and directions: ``solar_position`` of a latitude or Delta T given as text failed
inside JAX ("Error interpreting argument to _spa_jit"), of an altitude of None or a
complex latitude inside NumPy, took ``True`` as 1 degree, ``refraction="no"`` as True
(refraction applied), and a negative pressure or a temperature below absolute zero
(a refraction of its own, without a word). ``direction_to_azimuth_elevation`` of a
``(2,)`` vector returned an azimuth and an elevation (JAX clamps the index past the end);
``angle_between`` and ``reflect`` of a ``(2,)`` vector failed in JAX's broadcasting.

Benchmarks (their command lines are quoted in the README): ``--heliostats 0``,
``--repeats 0``, ``--instants -5``, ``--train-fraction 1.5``, ``--spreads nan`` and the
like were taken by ``type=int`` / ``type=float`` and failed as tracebacks after the
imports or the work (``min() arg is an empty sequence``); they now use the CLI's own
``integer`` / ``number`` types. ``discovery.py --out`` was written with ``open(..., "w")``
after each run (an interrupt while writing left half a JSON file under its name; a
folder as ``--out`` failed after the first run), and the ``--figure`` PNGs of
``flux_validation.py``, ``planning_study.py`` and ``real_reconstruction.py`` were
written in place; outputs are now checked before the work and written atomically.
heliojax's own outputs (results.h5, summary.json, report.json, figures) were checked
and are written atomically already (a PNG interrupted while drawing leaves nothing under
its name: tested below).

Ill-typed values are given under the ``unchecked`` fixture.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import run_cli

import heliojax as hj
from heliojax import effects as fx
from heliojax._errors import DataError
from heliojax._limits import MAX_FIT_STEPS
from heliojax._plotting import pyplot, save_figure
from heliojax._simulate import typical_actuators
from heliojax.discovery import discover
from heliojax.discovery._select import COUNT_OPTIONS
from heliojax.fitting import process_slice, robust_component_noise, robust_noise

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
STONE = {"alpha": 0.0, "beta": 0.0, "gamma": 0.0, "delta": 0.0, "theta_k": 0.0, "tau_k": 0.0, "gr1": 1.0, "gr2": 1.0}
ACTUATOR = {
    "alpha": 0.0,
    "beta": 0.0,
    "gamma": 0.0,
    "delta": 0.0,
    "angle_offset": np.zeros(2),
    "increment_scale": np.zeros(2),
    "stroke_offset": np.zeros(2),
}


@pytest.fixture(scope="module")
def fleet():
    """3 heliostats x 8 records of synthetic arrays (nothing here is fitted)."""
    k = jax.random.split(jax.random.PRNGKey(18), 2)
    geometry = hj.synthetic_geometry(k[0], 3)
    context = hj.synthetic_contexts(k[1], 3, 8)
    return hj.fleet_from_arrays(geometry, jnp.full((3, 8, 2), 3e4), context, jnp.zeros((3, 8, 3)))


def _benchmark(name: str):
    """The benchmark script ``benchmarks/<name>.py`` as a module (its imports are loaded)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCHMARKS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# --------------------------------------------------------------------------------------
# left open by earlier rounds
# --------------------------------------------------------------------------------------


def test_effects_built_directly_refuse_nan_and_inf_and_still_trace():
    for make, said in (
        (lambda: fx.Backlash(width=jnp.array([np.nan, 0.0]), stroke_width=jnp.zeros(2)), "Backlash.width must be"),
        (lambda: fx.GravitySag(sag=jnp.asarray(np.inf)), "GravitySag.sag must be finite"),
        (
            lambda: fx.Clock(offset=jnp.asarray(np.nan), drift=jnp.asarray(0.0), reference=1.65e9, latitude_deg=50.0),
            "Clock.offset must be finite",
        ),
        (lambda: fx.EncoderWobble(a=jnp.array([np.nan, 0.0]), b=jnp.zeros(2)), "EncoderWobble.coefficients"),
    ):
        with pytest.raises(ValueError, match=said):
            make()
    # traced values (discovery builds effects inside its compiled lanes) are not known: they pass
    assert bool(jnp.isnan(jax.jit(lambda s: fx.GravitySag(sag=s).sag)(jnp.asarray(np.nan))))
    assert fx.Backlash(width=jnp.array([3e-4, 0.0]), stroke_width=jnp.zeros(2)).width.shape == (2,)


def test_discover_of_a_fleet_without_a_valid_record_stops_at_once(fleet):
    """It had compiled and run for ~20 s, then failed inside NumPy."""
    empty = hj.fleet_from_arrays(
        fleet.geometry, fleet.counts, fleet.context, fleet.focal_spot, mask=np.zeros((3, 8), bool)
    )
    t0 = time.perf_counter()
    with pytest.raises(DataError, match=r"no valid calibration record in the fleet \(3 heliostats\)"):
        discover(empty)
    assert time.perf_counter() - t0 < 2.0


def test_discover_command_on_a_folder_without_a_record_names_it(tmp_path, capsys):
    data = tmp_path / "paint"
    shutil.copytree(hj.default_data_dir(), data)
    for folder in data.glob("*/Calibration"):
        shutil.rmtree(folder)
    rc, _, err = run_cli(["discover", str(data), "--report", str(tmp_path / "report.json"), "--quiet"], capsys)
    assert rc == 2 and "no valid calibration record" in err and str(data) in err, err
    assert "Traceback" not in err and not (tmp_path / "report.json").exists()


def test_the_fit_step_budget_has_one_bound(fleet, capsys):
    with pytest.raises(ValueError, match=f"max_steps: expected an integer >= 1 and <= {MAX_FIT_STEPS:,}"):
        hj.fit(hj.StoneModel.nominal(), fleet, max_steps=2**40)
    assert ("max_steps", 1, MAX_FIT_STEPS) in COUNT_OPTIONS  # discovery's bound is the same
    rc, _, err = run_cli(["calibrate", "--max-steps", str(MAX_FIT_STEPS + 1), "--quiet"], capsys)
    assert rc == 2 and "--max-steps" in err and "100000" in err.replace(",", ""), err


@pytest.mark.parametrize("n_free", [-1, 2.5, True, "3"])
def test_robust_noise_needs_a_count_of_free_parameters(unchecked, n_free):
    r = np.zeros((2, 4, 2))
    use = np.ones((2, 4), bool)
    for function in (robust_noise, robust_component_noise):
        with pytest.raises(ValueError, match=f"{function.__name__}: n_free"):
            function(r, use, n_free)


def test_process_slice_needs_whole_numbers(unchecked):
    for args, name in (((2.5, 0, 2), "n_heliostats"), ((True, 0, 1), "n_heliostats"), ((4, 1.5, 2), "process_index")):
        with pytest.raises(ValueError, match=f"process_slice: {name} must be a whole number"):
            process_slice(*args)
    assert process_slice(5, 1, 2) == slice(3, 5)


# --------------------------------------------------------------------------------------
# model pytrees built directly
# --------------------------------------------------------------------------------------


def test_a_model_of_python_numbers_is_a_model_of_arrays():
    """Python floats had been kept: ``fit`` then failed ("'float' object has no attribute
    'shape'"), since neither broadcasting nor the dtype conversion took them."""
    model = hj.StoneModel(**STONE | {"gr1": 1})
    assert all(isinstance(x, jax.Array) and x.dtype == jnp.float64 for x in jax.tree.leaves(model))
    assert hj.broadcast_model(model, 3).alpha.shape == (3,)
    act = hj.ActuatorModel(**ACTUATOR | {"angle_offset": [1e-3, 0.0]})
    np.testing.assert_array_equal(np.asarray(act.angle_offset), [1e-3, 0.0])


def test_model_parameters_of_another_kind_are_named(unchecked):
    for value in ("0.1", True, None, 1j, np.array(["a", "b"])):
        with pytest.raises(TypeError, match="StoneModel.alpha: expected real numbers"):
            hj.StoneModel(**STONE | {"alpha": value})
    with pytest.raises(TypeError, match="Thermal.reference: expected real numbers"):
        fx.Thermal(coefficient=jnp.zeros(2), expansion=jnp.zeros(2), reference="20")


def test_model_parameters_must_be_finite_and_in_their_range():
    for kind, values, said in (
        (hj.StoneModel, STONE | {"alpha": np.nan}, "StoneModel.alpha must be finite"),
        (hj.StoneModel, STONE | {"tau_k": -np.inf}, "StoneModel.tau_k must be finite"),
        (hj.StoneModel, STONE | {"gr1": 0.0}, "StoneModel.gr1 must be finite and > 0, got 0.0"),
        (hj.ActuatorModel, ACTUATOR | {"increment_scale": [0.0, -1.0]}, r"increment_scale must be finite and > -1"),
    ):
        with pytest.raises(ValueError, match=said):
            kind(**values)
    # a traced value is not known (a fit's step may cross the bound): it passes
    out = jax.vmap(lambda g: hj.StoneModel(**STONE | {"gr1": g}).gr1)(jnp.zeros(2))
    assert out.shape == (2,)


def test_model_parameters_of_another_shape_are_named():
    with pytest.raises(ValueError, match=r"ActuatorModel.angle_offset has shape \(3,\); expected \(2,\)"):
        hj.ActuatorModel(**ACTUATOR | {"angle_offset": np.zeros(3)})
    with pytest.raises(ValueError, match=r"ActuatorModel.angle_offset has shape \(\); expected \(2,\)"):
        hj.ActuatorModel(**ACTUATOR | {"angle_offset": 0.0})
    with pytest.raises(ValueError, match=r"StoneModel: its parameters are batched over different heliostat axes"):
        hj.StoneModel(**STONE | {"alpha": np.zeros((3, 1))})
    batched = hj.StoneModel(**{k: np.full(3, v) for k, v in STONE.items()})
    assert batched.gr2.shape == (3,)


def test_actuators_and_geometry_built_directly_refuse_what_they_cannot_mean(unchecked):
    act = typical_actuators()
    fields = {name: np.asarray(getattr(act, name)) for name in act.__dataclass_fields__}
    for name, value, said in (
        ("sign", np.zeros(2), r"sign must be \+1 or -1 \(clockwise_axis_movement 0 or 1\), got 0.0"),
        ("initial_angle", np.array([0.0, np.nan]), "initial_angle must be finite, got nan at axis 2"),
        ("max_counts", np.array([np.inf, 5e4]), "max_counts must be finite"),
    ):
        with pytest.raises(ValueError, match=f"LinearActuators: {said}"):
            hj.LinearActuators(**fields | {name: value})
    for ideal in (("no", "no"), (0.5, 0.0)):
        with pytest.raises(TypeError, match="HeliostatGeometry.build: ideal_axes must be booleans"):
            hj.HeliostatGeometry.build(jnp.zeros(3), act, ideal_axes=ideal)
    with pytest.raises(TypeError, match="HeliostatGeometry.build: position: expected ENU metres"):
        hj.HeliostatGeometry.build("0,0,0", act)
    with pytest.raises(ValueError, match="HeliostatGeometry.build: position must be finite"):
        hj.HeliostatGeometry.build(jnp.array([np.nan, 0.0, 0.0]), act)
    assert hj.HeliostatGeometry.build(jnp.zeros(3), act, ideal_axes=(1, 0)).ideal_axes.tolist() == [True, False]


# --------------------------------------------------------------------------------------
# the record container
# --------------------------------------------------------------------------------------


def test_a_fleet_built_directly_needs_a_boolean_mask_and_distinct_string_ids(fleet, unchecked):
    fields = {name: getattr(fleet, name) for name in fleet.__dataclass_fields__}
    for mask in (jnp.ones((3, 8)), jnp.ones(3, bool)):
        with pytest.raises(ValueError, match="Fleet.mask has shape .* expected booleans"):
            hj.Fleet(**fields | {"mask": mask})
    with pytest.raises(ValueError, match="Fleet.ids: heliostat id 'a' is listed twice"):
        hj.Fleet(**fields | {"ids": ("a", "a", "c")})
    with pytest.raises(ValueError, match=r"Fleet.ids: heliostat ids are strings, got 1 \(int\)"):
        hj.Fleet(**fields | {"ids": (1, 2, 3)})
    assert hj.Fleet(**fields | {"ids": ("a", "", "")}).ids == ("a", "", "")  # "": padding heliostats


def test_fleet_from_arrays_names_an_array_of_another_shape(fleet, unchecked):
    g, c, x, f = fleet.geometry, fleet.context, fleet.counts, fleet.focal_spot
    for args, said in (
        ((g, x[:, 0], c, f), r"counts has shape \(3, 2\); expected \(H, M, 2\)"),
        ((g, x, c, f[:, :7]), r"focal_spot has shape \(3, 7, 3\); expected \(3, 8, 3\)"),
        ((g, x[:, :7], c, f[:, :7]), r"context.sun has shape \(3, 8, 3\); expected \(3, 7, 3\)"),
        ((jax.tree.map(lambda a: a[0], g), x, c, f), r"geometry.position has shape \(3,\); expected \(3, 3\)"),
    ):
        with pytest.raises(ValueError, match=f"fleet_from_arrays: {said}"):
            hj.fleet_from_arrays(*args)
    with pytest.raises(ValueError, match=r"fleet_from_arrays: mask has shape \(8,\)"):
        hj.fleet_from_arrays(g, x, c, f, mask=np.ones(8, bool))
    for args, name in (((None, x, c, f), "geometry"), ((g, x, None, f), "context")):
        with pytest.raises(TypeError, match=f"fleet_from_arrays: {name}: expected a batched heliojax"):
            hj.fleet_from_arrays(*args)


def test_fleet_from_arrays_takes_heliostat_ids_only(fleet, unchecked):
    g, c, x, f = fleet.geometry, fleet.context, fleet.counts, fleet.focal_spot
    for ids, said in (
        (["a", "", "c"], "'' is no heliostat id: blank"),
        (["a,b", "x", "c"], "'a,b' is no heliostat id: holds a comma"),
    ):
        with pytest.raises(ValueError, match=f"ids: {said}"):
            hj.fleet_from_arrays(g, x, c, f, ids=ids)
    with pytest.raises(TypeError, match=r"ids: heliostat ids are strings, got 1 \(int\)"):
        hj.fleet_from_arrays(g, x, c, f, ids=[1, 2, 3])


def test_pad_fleet_sizes_and_heliostat_positions_are_whole_numbers(fleet, unchecked):
    for sizes, said in (
        ((8.5,), "n_heliostats must be a whole number, got 8.5"),
        ((None, True), "n_records must be a whole number, got True"),
        (("16",), "n_heliostats must be a whole number, got '16'"),
        ((10**12,), "n_heliostats must be at most 1,000,000"),
    ):
        with pytest.raises(ValueError, match=f"pad_fleet: {said}"):
            hj.pad_fleet(fleet, *sizes)
    assert hj.pad_fleet(fleet, 4, 8).n_heliostats == 4
    for i in (True, 1.7, None):
        with pytest.raises(TypeError, match="Fleet.heliostat: expected a heliostat position"):
            fleet.heliostat(i)
    assert fleet.heliostat(np.int64(1)).id == "H001" and fleet.heliostat("H002").id == "H002"


# --------------------------------------------------------------------------------------
# the sun and directions
# --------------------------------------------------------------------------------------


def test_solar_position_names_an_argument_that_is_no_number(unchecked):
    t = 1.65e9
    for kwargs, name in (
        ({"latitude_deg": "50"}, "latitude_deg"),
        ({"latitude_deg": True}, "latitude_deg"),
        ({"latitude_deg": 50 + 1j}, "latitude_deg"),
        ({"altitude_m": None}, "altitude_m"),
        ({"delta_t_s": "69"}, "delta_t_s"),
    ):
        args = {"latitude_deg": 50.9, "longitude_deg": 6.4} | kwargs
        with pytest.raises(TypeError, match=f"solar_position: {name} must be real numbers"):
            hj.solar_position(t, **args)
    with pytest.raises(TypeError, match="solar_position: refraction must be True or False, got 'no'"):
        hj.solar_position(t, 50.9, 6.4, refraction="no")


def test_solar_position_refuses_an_impossible_atmosphere():
    with pytest.raises(ValueError, match=r"pressure_hpa must be in \[0, inf\], not -1000"):
        hj.solar_position(1.65e9, 50.9, 6.4, pressure_hpa=-1000.0)
    with pytest.raises(ValueError, match=r"temperature_c must be in \[-273.15, inf\]"):
        hj.solar_position(1.65e9, 50.9, 6.4, temperature_c=np.array([12.0, -300.0]))


def test_direction_helpers_need_vectors_of_three(unchecked):
    with pytest.raises(
        ValueError,
        match=r"direction_to_azimuth_elevation: direction has shape \(2,\); expected \(\.\.\., 3\) ENU vectors",
    ):
        hj.direction_to_azimuth_elevation(jnp.array([0.0, 1.0]))
    with pytest.raises(ValueError, match=r"angle_between: b has shape \(2,\)"):
        hj.angle_between(jnp.ones(3), jnp.ones(2))
    with pytest.raises(ValueError, match=r"reflect: normal has shape \(4, 2\)"):
        hj.reflect(jnp.ones((4, 3)), jnp.ones((4, 2)))


# --------------------------------------------------------------------------------------
# benchmark command lines and interrupted outputs
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("script", "argv", "said"),
    [
        ("aim_speed", ["--heliostats", "0"], "argument --heliostats: 0 is outside [1,"),
        ("aim_speed", ["--repeats", "0"], "argument --repeats: 0 is outside [1,"),
        ("calibration_speed", ["--train-fraction", "1.5"], "argument --train-fraction: 1.5 is outside (0.0, 1.0)"),
        ("noise_outlier_rates", ["--spreads", "0.2", "nan"], "argument --spreads: nan"),
        ("raytrace_speed", ["--rays", "-5"], "argument --rays"),
    ],
)
def test_benchmark_command_lines_refuse_counts_and_numbers_out_of_range(monkeypatch, capsys, script, argv, said):
    module = _benchmark(script)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", *argv])
    with pytest.raises(SystemExit) as stop:
        module.parse_args(argv) if script == "calibration_speed" else module.main()
    assert stop.value.code == 2 and said in capsys.readouterr().err


def test_benchmark_output_is_checked_first_and_written_whole(tmp_path, monkeypatch, capsys):
    """discovery.py had opened --out with "w" after each run: an interrupt while the JSON
    was written left half a file under its name; a folder failed after the first run."""
    bench = _benchmark("discovery")
    with pytest.raises(SystemExit) as stop:
        bench.main(["--out", str(tmp_path), "--seeds", "1"])
    assert stop.value.code == 2 and "--out" in capsys.readouterr().err
    out = tmp_path / "runs.json"
    out.write_text('{"previous": true}\n')
    monkeypatch.setattr(bench, "run_one", lambda name, seed, h, m: {"scenario": name, "seed": seed})
    monkeypatch.setattr(bench, "summarise", lambda runs: {"runs": len(runs)})
    real_dump = json.dump

    def interrupted(obj, f, **kwargs):  # a Ctrl-C while the file is being written
        f.write('{"summary": ')
        raise KeyboardInterrupt

    monkeypatch.setattr(json, "dump", interrupted)
    with pytest.raises(KeyboardInterrupt):
        bench.main(["--out", str(out), "--seeds", "1", "--scenarios", "null"])
    monkeypatch.setattr(json, "dump", real_dump)
    assert json.loads(out.read_text()) == {"previous": True}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs.json"]  # no temporary left


def test_a_figure_interrupted_while_drawing_leaves_nothing_under_its_name(tmp_path):
    """heliojax's figures go through one atomic writer (benchmarks now too)."""
    fig = pyplot().figure()

    def interrupted(path, **kwargs):
        Path(path).write_bytes(b"\x89PNG half")
        raise KeyboardInterrupt

    fig.savefig = interrupted
    with pytest.raises(KeyboardInterrupt):
        save_figure(fig, tmp_path / "figure.png")
    assert list(tmp_path.iterdir()) == []
