"""Hostile-input round 14: what a notebook user calls after a fit (aiming, planning) and
HDF5 files that read data from outside themselves.

HDF5: a results.h5 or ARTIST scenario whose dataset or group is an external link (to
another, valid file), a dataset stored in external raw files, or a virtual dataset was
read without a word: the data came from a file the messages never named. Each is now a
:class:`~heliojax.DataError` naming the file and the HDF5 path; an ARTIST heliostat
that is such a link (or a dangling one) no longer spoils the others under ``skip_bad``.

Planning: ``plan_calibration`` of a path, of candidates of other heliostats or of none
(K = 0), a budget of 10**9, candidates of NaN counts (chosen, a measurement wasted),
``candidates_from_records`` of a string or an empty list, ``candidates_at_targets`` of
a ``(3,)`` or NaN sun, ``predicted_uncertainty_mrad`` of mismatched shapes; aiming:
``aim_results`` with a misspelled option. Each had been an AttributeError, a vmap,
argmax or einsum error, an error naming another function, a hang, or a silent result.

Ill-typed values are given under the ``unchecked`` fixture."""

from __future__ import annotations

import shutil

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHARED_PAINT

import heliojax as hj
from heliojax._errors import DataError
from heliojax._plan import Candidates, plan_measurements
from heliojax.paint import read_artist_scenario

SCENARIO = SHARED_PAINT.parent / "artist-scenarios" / "paint_four_heliostats_ideal.h5"
SUN = np.asarray([[0.3, -0.5, 0.81], [0.5, 0.2, 0.7], [-0.4, -0.3, 0.6]])
SUN = SUN / np.linalg.norm(SUN, axis=1, keepdims=True)
CENTRES = jnp.asarray([[0.0, 0.0, 50.0], [5.0, 0.0, 40.0]])
ENVELOPE_SUN = jnp.asarray(SUN)
ENVELOPE_WEIGHT = jnp.ones(3)
AIM = jnp.asarray([0.0, 0.0, 50.0])


# --------------------------------------------------------------------------------------
# HDF5 data from outside the file
# --------------------------------------------------------------------------------------


def _results_linked(fitted_h5, tmp_path, name: str):
    other = tmp_path / "other.h5"
    shutil.copy(fitted_h5, other)
    results = tmp_path / "results.h5"
    shutil.copy(fitted_h5, results)
    with h5py.File(results, "r+") as f:
        del f[name]
        f[name] = h5py.ExternalLink(str(other), name)
    return results


@pytest.mark.parametrize("name", ["params", "geometry"])
def test_load_results_refuses_an_external_link_to_another_valid_file(fitted_h5, tmp_path, name):
    results = _results_linked(fitted_h5, tmp_path, name)
    with pytest.raises(DataError, match=rf"results.h5: field '{name}': holds data from outside this file"):
        hj.load_results(results)


def test_load_results_refuses_a_dataset_stored_in_a_raw_file(fitted_h5, tmp_path):
    results = tmp_path / "results.h5"
    shutil.copy(fitted_h5, results)
    with h5py.File(results, "r+") as f:
        params = f["params"][()]
        (tmp_path / "raw.bin").write_bytes(params.tobytes())
        del f["params"]
        f.create_dataset("params", shape=params.shape, dtype=params.dtype, external=[("raw.bin", 0, params.nbytes)])
    with pytest.raises(DataError, match=r"field 'params': .*stored in external file\(s\) \['raw.bin'\]"):
        hj.load_results(results)
    assert hj.load_results(fitted_h5).ids  # the file itself is read


def test_artist_reader_refuses_an_external_heliostat_and_skips_only_it(tmp_path):
    if not SCENARIO.exists():
        pytest.skip(f"no ARTIST scenario at {SCENARIO}")
    linked, other = tmp_path / "a.h5", tmp_path / "b.h5"
    shutil.copy(SCENARIO, linked)
    shutil.copy(SCENARIO, other)
    with h5py.File(linked, "r+") as f:
        names = list(f["heliostats"])
        del f["heliostats"][names[1]]
        f["heliostats"][names[1]] = h5py.ExternalLink(str(other), f"/heliostats/{names[1]}")
        f["heliostats"]["dangling"] = h5py.SoftLink("/nowhere")
    with pytest.raises(DataError, match=rf"field 'heliostats/{names[1]}': holds data from outside this file"):
        read_artist_scenario(linked)
    scenario = read_artist_scenario(linked, skip_bad=True)  # each bad entry had spoilt every heliostat
    assert [h.name for h in scenario.heliostats] == [n for n in names if n != names[1]]
    assert {name for name, _ in scenario.skipped} == {names[1], "dangling"}


def test_artist_reader_refuses_a_virtual_dataset(tmp_path):
    if not SCENARIO.exists():
        pytest.skip(f"no ARTIST scenario at {SCENARIO}")
    path = tmp_path / "a.h5"
    shutil.copy(SCENARIO, path)
    with h5py.File(tmp_path / "src.h5", "w") as src:
        src["x"] = np.asarray([50.9, 6.38, 87.0])
    with h5py.File(path, "r+") as f:
        layout = h5py.VirtualLayout(shape=(3,), dtype="f8")
        layout[:] = h5py.VirtualSource(str(tmp_path / "src.h5"), "x", shape=(3,))
        del f["power_plant/position"]
        f["power_plant"].create_virtual_dataset("position", layout)
    with pytest.raises(DataError, match=r"field 'power_plant/position': .*a virtual dataset"):
        read_artist_scenario(path)


# --------------------------------------------------------------------------------------
# Planning and aiming after a fit
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def results(fitted_h5):
    return hj.load_results(fitted_h5)


@pytest.fixture(scope="module")
def candidates(results):
    return hj.candidates_at_targets(results.model, results.geometry, jnp.asarray(SUN), CENTRES)


def _plan(results, candidates, **kw):
    kw = {"envelope_sun": ENVELOPE_SUN, "envelope_weight": ENVELOPE_WEIGHT, "aim_point": AIM, "budget": 2} | kw
    return hj.plan_calibration(results, candidates, **kw)


def test_plan_calibration_names_a_path_or_none_given_for_its_inputs(results, candidates, fitted_h5, unchecked):
    with pytest.raises(TypeError, match=r"results: expected a CalibrationResults .*got PosixPath"):
        _plan(fitted_h5, candidates)
    with pytest.raises(TypeError, match=r"candidates: expected Candidates .*got NoneType"):
        _plan(results, None)


def test_plan_calibration_refuses_candidates_of_other_heliostats(results, candidates):
    fewer = jax.tree.map(lambda x: x[:2], candidates)
    with pytest.raises(ValueError, match=r"candidates are for \(2,\) heliostat\(s\).*the results hold 5"):
        _plan(results, fewer)


def test_plan_refuses_a_budget_of_a_billion_and_no_candidates():
    h, k, f = 2, 3, 4
    cov, env = jnp.broadcast_to(jnp.eye(f), (h, f, f)), jnp.broadcast_to(jnp.eye(f), (h, f, f))
    jac, valid = jnp.ones((h, k, 2, f)), jnp.ones((h, k), bool)
    with pytest.raises(ValueError, match=r"budget must be a whole number of measurements in \[0, 100,000\]"):
        plan_measurements(cov, jac, valid, env, 1.0, 10**9)
    with pytest.raises(ValueError, match=r"candidates: none \(K = 0"):
        plan_measurements(cov, jac[:, :0], valid[:, :0], env, 1.0, 2)
    plan = plan_measurements(cov, jac, valid, env, 1.0, 5)  # more than K: padded, not run past K
    assert plan.chosen.shape == (h, 5) and (np.asarray(plan.chosen[:, 3:]) == -1).all()


def test_plan_calibration_never_chooses_a_candidate_of_nan_counts(results, candidates):
    bad = Candidates(
        counts=candidates.counts.at[0].set(jnp.nan),
        context=candidates.context,
        spots=candidates.spots,
        valid=candidates.valid,
        slot=candidates.slot,
    )
    plan, _ = _plan(results, bad)
    good, _ = _plan(results, candidates)
    chosen = np.asarray(plan.chosen)
    assert (chosen[0] == -1).all()  # had chosen two candidates of NaN counts, a zero Jacobian
    np.testing.assert_array_equal(chosen[1:], np.asarray(good.chosen)[1:])


def test_candidates_name_their_sun_and_ids(results, unchecked):
    with pytest.raises(ValueError, match=r"sun has shape \(3,\); expected \(N, 3\)"):
        hj.candidates_at_targets(results.model, results.geometry, jnp.asarray(SUN[0]), CENTRES)
    with pytest.raises(ValueError, match=r"sun: 1 vector\(s\) are not finite unit vectors"):
        hj.candidates_at_targets(results.model, results.geometry, jnp.asarray(SUN).at[0, 0].set(jnp.nan), CENTRES)
    fleet = hj.load_paint_directory(hj.default_data_dir())
    with pytest.raises(TypeError, match=r"ids: expected a sequence of heliostat ids .*got str"):
        hj.candidates_from_records(fleet, "BE36")
    none, record_ids = hj.candidates_from_records(fleet, [])  # had been an IndexError
    assert none.valid.shape[0] == 0 and record_ids.shape[0] == 0


def test_predicted_uncertainty_names_mismatched_shapes(unchecked):
    with pytest.raises(ValueError, match=r"covariance \(2, 3, 3\) and envelope \(3, 3, 3\) must both be"):
        hj.predicted_uncertainty_mrad(jnp.zeros((2, 3, 3)), jnp.zeros((3, 3, 3)))


def test_aim_results_names_a_misspelled_option(results):
    with pytest.raises(TypeError, match=r"unknown option\(s\) max_sky_gap; the options are max_sky_gap_deg"):
        hj.aim_results(results, jnp.asarray(SUN), AIM, max_sky_gap=3.0)
