"""Traced programs kept across processes (heliojax._programs): same results as a
fresh trace, loaded instead of traced, keyed by every static option and shape; their
compiled executables kept too, keyed by the compiler's settings, and loaded in the
background for a command's next run."""

from __future__ import annotations

import copy
import json
import os
import pickle
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import zoo

import heliojax as hj
from heliojax import _programs
from heliojax.fitting import CompiledFit, FitSolution, find_change_points, fleet_residuals_mrad


@pytest.fixture
def program_dir(tmp_path, monkeypatch):
    """A program directory for this test only (no global JAX cache configured)."""
    monkeypatch.setattr(_programs, "_program_dir", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_COMPILED", {})
    return tmp_path


def _no_export(*_a, **_k):
    raise AssertionError("traced again although a kept program exists")


def _drop_executables(program_dir):
    """Remove the kept executables (as another compiler setting would find none): the
    traced programs are loaded and compiled."""
    for path in program_dir.glob("*.exe"):
        path.unlink()


def test_kept_fit_program_gives_the_traced_result(program_dir, monkeypatch):
    fleet = zoo("actuator").fleet
    model0 = hj.ActuatorModel.nominal()
    reference = CompiledFit(model0, fleet, max_steps=16)(model0)  # traced here: a program is written
    written = sorted(program_dir.glob("*.bin"))
    assert len(written) == 1
    monkeypatch.setattr(_programs, "_export", _no_export)  # from now on only loading is allowed
    for drop in (False, True):  # the kept executable, then the kept traced program compiled again
        if drop:
            _drop_executables(program_dir)
        _programs._COMPILED.clear()  # as a new process: load from the directory
        kept = CompiledFit(model0, fleet, max_steps=16)(model0)
        for a, b in zip(jax.tree.leaves(reference.model), jax.tree.leaves(kept.model), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(reference.status), np.asarray(kept.status))
        np.testing.assert_array_equal(np.asarray(reference.covariance), np.asarray(kept.covariance))
    assert sorted(program_dir.glob("*.bin")) == written


def test_a_program_compiled_in_this_process_is_not_lowered_again(monkeypatch):
    """The same key in one process (the CLI fits, validates the drift and refits after
    a change point with one program) returns the compiled program itself, with or
    without a cache directory."""
    monkeypatch.setattr(_programs, "_COMPILED", {})
    fleet = zoo("actuator").fleet
    model0 = hj.ActuatorModel.nominal()
    monkeypatch.setattr(_programs, "_program_dir", lambda: None)
    first = CompiledFit(model0, fleet, max_steps=16)
    lowered = []
    original = _programs._compile
    monkeypatch.setattr(_programs, "_compile", lambda *a: lowered.append(1) or original(*a))
    second = CompiledFit(model0, fleet, max_steps=16)
    assert lowered == [] and second._compiled is first._compiled
    third = CompiledFit(model0, fleet, max_steps=15)  # another static option: compiled
    assert lowered == [1] and third._compiled is not first._compiled
    a, b = first(model0), second(model0)
    np.testing.assert_array_equal(np.asarray(a.status), np.asarray(b.status))


def test_other_static_option_or_shape_is_another_program(program_dir):
    """The key covers the static arguments (as CompiledFit's ``max_steps``), the
    shapes and the dtypes; the same call again loads (no new program)."""
    power = _programs.cached_jit(_power)
    x = jnp.arange(4.0)
    for args in ((x, 2), (x, 3), (jnp.arange(6.0), 2), (x.astype(jnp.float32), 2), (x, 2)):
        np.testing.assert_array_equal(np.asarray(power(*args)), np.asarray(args[0]) ** args[1])
    assert len(list(program_dir.glob("*.bin"))) == 4


def test_edited_source_is_another_program(program_dir, monkeypatch):
    """An edited checkout (same version number) never loads a program traced from
    the old source: the key holds a digest of heliojax's source files."""
    assert len(_programs.source_digest()) == 64
    power = _programs.cached_jit(_power)
    x = jnp.arange(3.0)
    power(x, 2)
    assert len(list(program_dir.glob("*.bin"))) == 1
    monkeypatch.setattr(_programs, "source_digest", lambda: "edited")
    power(x, 2)
    assert len(list(program_dir.glob("*.bin"))) == 2


def test_damaged_program_is_traced_again_and_replaced(program_dir):
    errors = jnp.arange(6.0).reshape(2, 3)
    square = _programs.cached_jit(_square)
    expected = np.asarray(errors) ** 2
    np.testing.assert_array_equal(np.asarray(square(errors)), expected)
    (path,) = program_dir.glob("*.bin")
    path.write_bytes(b"not a program")
    _drop_executables(program_dir)
    _programs._COMPILED.clear()
    np.testing.assert_array_equal(np.asarray(square(errors)), expected)
    assert path.read_bytes() != b"not a program"


def test_a_program_kept_under_another_key_is_not_run(program_dir):
    """Files of the program directory swapped round (each key holding another valid
    program, e.g. copied between caches): each call traces its own program again, with
    its own result, instead of running the other's (or failing on its arguments)."""
    power = _programs.cached_jit(_power)
    x, y = jnp.arange(4.0), jnp.arange(6.0).reshape(2, 3)
    power(x, 2)
    power(y, 3)
    first, second = sorted(program_dir.glob("*.bin"))
    blobs = first.read_bytes(), second.read_bytes()
    first.write_bytes(blobs[1])
    second.write_bytes(blobs[0])
    _drop_executables(program_dir)
    _programs._COMPILED.clear()
    np.testing.assert_array_equal(np.asarray(power(x, 2)), np.asarray(x) ** 2)
    np.testing.assert_array_equal(np.asarray(power(y, 3)), np.asarray(y) ** 3)
    for path in (first, second):  # each traced again and rewritten under its own key
        assert pickle.loads(path.read_bytes())[0] == path.stem


def test_lambdas_are_never_kept(program_dir):
    square = _programs.cached_jit(lambda x: x**2)
    np.testing.assert_array_equal(np.asarray(square(jnp.arange(3.0))), [0.0, 1.0, 4.0])
    assert list(program_dir.glob("*.bin")) == []


def test_without_a_cache_directory_nothing_is_written(tmp_path, monkeypatch):
    monkeypatch.setattr(_programs, "_program_dir", lambda: None)
    monkeypatch.setattr(_programs, "_export", _no_export)
    square = _programs.cached_jit(_square)
    np.testing.assert_array_equal(np.asarray(square(jnp.arange(3.0))), [0.0, 1.0, 4.0])


def test_a_program_compiled_by_another_thread_is_waited_for(program_dir, monkeypatch):
    """Two threads asking for one key compile it once; the second waits for the first
    and runs the same program (the warm-up thread and the caller)."""
    compiled = []
    started = threading.Event()
    original = _programs._compile

    def slow(*a):
        compiled.append(1)
        started.set()
        time.sleep(0.3)  # the other thread asks meanwhile
        return original(*a)

    monkeypatch.setattr(_programs, "_compile", slow)
    power = _programs.cached_jit(_power)
    x = jnp.arange(5.0)
    results = {}
    worker = threading.Thread(target=lambda: results.setdefault("worker", power(x, 3)))
    worker.start()
    assert started.wait(60)
    results["caller"] = power(x, 3)
    worker.join(60)
    assert compiled == [1]
    for r in results.values():
        np.testing.assert_array_equal(np.asarray(r), np.asarray(x) ** 3)
    assert len(results) == 2


def test_a_failed_compile_in_another_thread_is_compiled_again_by_the_caller(program_dir, monkeypatch):
    original = _programs._compile
    calls = []

    def first_fails(*a):
        calls.append(threading.current_thread().name)
        if len(calls) == 1:
            raise RuntimeError("compiler ran out of memory")
        return original(*a)

    monkeypatch.setattr(_programs, "_compile", first_fails)
    square = _programs.cached_jit(_square)
    done = _programs.warm_up(lambda: square(jnp.arange(3.0)))
    done.result(60)  # the failure is swallowed (logged at debug level)
    np.testing.assert_array_equal(np.asarray(square(jnp.arange(3.0))), [0.0, 1.0, 4.0])
    assert len(calls) == 2 and calls[0].startswith("heliojax-warm-up") and calls[1] == threading.current_thread().name


def test_warm_up_runs_with_the_callers_float64_setting():
    assert _programs.warm_up(lambda: jnp.asarray(1.0).dtype).result(60) is None  # results are discarded
    got = []
    with jax.enable_x64(False):
        _programs.warm_up(lambda: got.append(jnp.asarray(1.0).dtype)).result(60)
    _programs.warm_up(lambda: got.append(jnp.asarray(1.0).dtype)).result(60)
    assert got == [jnp.float32, jnp.float64]


def test_a_warm_up_started_from_a_warm_up_runs_at_once():
    """The warm-up thread is one: work that starts another warm-up and waits for it
    (e.g. a workflow run as another's warm-up) must not wait for itself."""
    order = []

    def outer():
        _programs.warm_up(lambda: order.append("inner")).result(60)
        order.append("outer")

    _programs.warm_up(outer).result(60)
    assert order == ["inner", "outer"]


def test_a_placeholder_solution_has_the_key_of_a_fit(program_dir, monkeypatch):
    """What the warm-up compiles on a placeholder fit is the program the real fit's
    solution then runs: same static parts, shapes and dtypes (the same key)."""
    fleet = zoo("actuator").fleet
    model0 = hj.ActuatorModel.nominal()
    weights = jax.device_put(np.ones(fleet.mask.shape))
    placeholder = FitSolution.placeholder(model0, fleet)
    fleet_residuals_mrad(placeholder.model, fleet)
    find_change_points(placeholder, fleet, fleet.mask, weights)  # residuals, their Jacobians, the scan
    assert len(list(program_dir.glob("*.bin"))) == 3
    monkeypatch.setattr(_programs, "_compile", _no_export)  # the fit's solution must find them compiled
    solution = hj.fit(model0, fleet, max_steps=16)
    r = np.asarray(fleet_residuals_mrad(solution.model, fleet))
    assert np.isfinite(r[np.asarray(fleet.mask)]).all()
    changes = find_change_points(solution, fleet, fleet.mask, weights)
    assert np.isfinite(np.asarray(changes.delta_chi2)).any()
    assert np.asarray(placeholder.status).tolist() == [0] * fleet.counts.shape[0]
    for a, b in zip(jax.tree.leaves(placeholder), jax.tree.leaves(solution), strict=True):
        assert np.shape(a) == np.shape(b) and np.asarray(a).dtype == np.asarray(b).dtype


def test_a_kept_executable_runs_without_lowering_or_compiling(program_dir, monkeypatch):
    solve = _programs.cached_jit(_solve)
    a, b = jnp.array([[4.0, 1.0], [1.0, 3.0]]), jnp.array([1.0, 2.0])
    reference = np.asarray(solve(a, b))
    assert len(list(program_dir.glob("*.exe"))) == 1 and len(list(program_dir.glob("*.bin"))) == 1
    _programs._COMPILED.clear()
    monkeypatch.setattr(_programs, "_compile_noting_cache_hits", _no_export)
    monkeypatch.setattr(_programs, "_export", _no_export)
    np.testing.assert_array_equal(np.asarray(solve(a, b)), reference)
    np.testing.assert_allclose(reference, np.linalg.solve(np.asarray(a), np.asarray(b)), rtol=1e-14)


def test_a_damaged_executable_is_compiled_again_and_replaced(program_dir):
    square = _programs.cached_jit(_square)
    x = jnp.arange(4.0)
    square(x)
    (path,) = program_dir.glob("*.exe")
    blob = bytearray(path.read_bytes())
    blob[-100] ^= 0xFF  # inside the executable's bytes: the digest no longer matches
    path.write_bytes(bytes(blob))
    _programs._COMPILED.clear()
    np.testing.assert_array_equal(np.asarray(square(x)), np.asarray(x) ** 2)
    assert path.read_bytes() != bytes(blob)
    assert _programs._read_executable(path) is not None


def test_compiler_settings_key_the_executable_not_the_traced_program(program_dir, monkeypatch):
    """Another XLA flag or optimisation setting is another executable of the same
    kept traced program."""
    square = _programs.cached_jit(_square)
    x = jnp.arange(3.0)
    square(x)
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_fast_math=false")
    _programs._COMPILED.clear()
    square(x)
    setting = jax.config.values["jax_disable_most_optimizations"]
    try:
        jax.config.update("jax_disable_most_optimizations", not setting)
        _programs._COMPILED.clear()
        np.testing.assert_array_equal(np.asarray(square(x)), np.asarray(x) ** 2)
    finally:
        jax.config.update("jax_disable_most_optimizations", setting)
    assert len(list(program_dir.glob("*.exe"))) == 3 and len(list(program_dir.glob("*.bin"))) == 1


_PROCESS = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from heliojax.cli._common import enable_compilation_cache
    from heliojax import _programs
    from test_programs import _solve
    enable_compilation_cache(sys.argv[1], "test")
    if sys.argv[2] == "load":  # nothing may be lowered or compiled
        def refuse(*a, **k):
            raise AssertionError("compiled although an executable is kept")
        _programs._compile_noting_cache_hits = refuse
    device = jax.devices()[int(sys.argv[3])]
    a, b = jax.device_put(jnp.array([[4.0, 1.0], [1.0, 3.0]]), device), jax.device_put(jnp.array([1.0, 2.0]), device)
    x = _programs.cached_jit(_solve)(a, b, "first")
    out = {
        "x": np.asarray(x).tolist(),
        "device": [d.id for d in x.devices()],
        "preloaded": sorted(p.name for p in _programs._PRELOADED),
    }
    if sys.argv[2] != "load":  # another key, the same program: a hit of JAX's cache, not kept
        y = _programs.cached_jit(_solve)(a, b, "second")
        out["same"] = np.asarray(y).tolist() == out["x"]
    _programs.remember("test")
    print(json.dumps(out))
    """
)


def test_executables_reach_the_next_process_loaded_in_the_background(tmp_path):
    """A second process loads the kept executables (with a LAPACK call: its kernels are
    bound first, or the process would crash) in the background and compiles nothing.
    The second key's program is the first's: JAX's cache has it, and an executable JAX
    loaded from there would be written without its kernels on XLA:CPU, so it is not
    kept. Arrays on another device (two CPU devices here) get executables of their own
    (one loaded for the other device crashed the process)."""
    env = dict(
        os.environ,
        JAX_NUM_CPU_DEVICES="2",
        PYTHONPATH=os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]),
    )
    runs = []
    for mode, device in (("compile", 0), ("load", 0), ("other device", 1), ("load", 1)):
        done = subprocess.run(
            [sys.executable, "-c", _PROCESS, str(tmp_path), mode, str(device)],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr[-3000:]
        runs.append(json.loads(done.stdout.splitlines()[-1]))
    programs = tmp_path / _programs.PROGRAM_DIR
    assert all(r.get("same", True) and r["x"] == runs[0]["x"] for r in runs)
    assert runs[0]["same"] and runs[2]["same"]
    assert [r["device"] for r in runs] == [[0], [0], [1], [1]]
    assert len(list(programs.glob("*.bin"))) == 2  # two keys, two traced programs
    assert len(list(programs.glob("*.exe"))) == 2  # the first key's, on each device
    # each run lists what it ran; the next loads it in the background and takes it, except
    # the run on the other device, which leaves the previous run's executable unused
    assert len((programs / "test.recent").read_text().split()) == 1
    assert [len(r["preloaded"]) for r in runs] == [0, 0, 1, 0]


_CALIBRATE = textwrap.dedent(
    """
    import json, sys
    import jax.monitoring
    requests = []
    COMPILE = "/jax/compilation_cache/compile_requests_use_cache"
    jax.monitoring.register_event_listener(lambda event, **_: requests.append(event) if event == COMPILE else None)
    from heliojax.cli._main import main
    rc = main(["calibrate", "--quiet", "--report", sys.argv[1], "--cache-dir", sys.argv[2]])
    print(json.dumps({"rc": rc, "compiled": len(requests)}))
    """
)


def test_a_second_calibrate_compiles_nothing_and_reports_the_same(tmp_path):
    """The command line's warm run (a new process, the cache of a first run): every
    program is a kept executable, so nothing is lowered or compiled (not even an eager
    operation: JAX's compile requests counted), and the summary is the first run's."""
    runs, reports = [], []
    for i in range(2):
        report = tmp_path / f"summary{i}.json"
        done = subprocess.run(
            [sys.executable, "-c", _CALIBRATE, str(report), str(tmp_path / "cache")],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, done.stderr[-3000:]
        runs.append(json.loads(done.stdout.splitlines()[-1]))
        reports.append(json.loads(report.read_text()))
    assert runs[0]["rc"] == runs[1]["rc"] == 0
    assert runs[0]["compiled"] > 5 and runs[1]["compiled"] == 0
    listed = (tmp_path / "cache" / _programs.PROGRAM_DIR / f"calibrate{_programs.RECENT_SUFFIX}").read_text().split()
    assert len(listed) > 5 and all((tmp_path / "cache" / _programs.PROGRAM_DIR / name).exists() for name in listed)
    for first, second in zip(reports[0]["heliostats"].values(), reports[1]["heliostats"].values(), strict=True):
        assert first == second
    assert {k: v for k, v in reports[0]["fleet"].items() if not k.endswith("_s")} == {
        k: v for k, v in reports[1]["fleet"].items() if not k.endswith("_s")
    }


def test_the_key_does_not_depend_on_shared_objects():
    """Static parts that are one object in one call and equal copies in another (a
    traced program's outputs share its inputs' static parts, a loaded one's do not)
    have one key; other values have another."""
    view = hj.ActuatorModel.nominal()
    same = _programs._key(_power, (view, view), [])
    assert same is not None and same == _programs._key(_power, (view, copy.deepcopy(view)), [])
    assert same != _programs._key(_power, (view, hj.StoneModel.nominal()), [])


def test_remember_lists_only_what_this_command_ran(program_dir):
    square = _programs.cached_jit(_square)
    square(jnp.arange(2.0))
    _programs.preload("first")  # nothing listed yet: starts nothing, forgets what ran before
    _programs.remember("first")
    assert not (program_dir / "first.recent").exists()
    square(jnp.arange(3.0))
    _programs.remember("first")
    (kept,) = [p for p in program_dir.glob("*.exe") if _programs._read_executable(p)[0].in_avals[0][0].shape == (3,)]
    assert (program_dir / "first.recent").read_text().split() == [kept.name]


def _solve(a, b, note: str = ""):  # ``note``: a static argument that changes the key, not the program
    del note
    return jnp.linalg.solve(a, b)


def _square(x):
    return x**2


def _power(x, n: int):
    return x**n


def test_own_cpu_programs_compile_with_the_older_emitters_unless_told_otherwise(monkeypatch):
    """``program_jit`` hands its CPU compilation the options of
    ``_xla_flags.cpu_compiler_options`` (XLA's older fusion emitters) and no flag of
    the process changes; ``XLA_FLAGS`` naming the option (the user's choice; the suite's
    conftest sets it, cleared here) or a jaxlib before the newer emitters give none.
    The options reach XLA (an unknown one is refused at compile time), and the results
    equal XLA's defaults'."""
    from heliojax import _xla_flags

    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    monkeypatch.setattr(_xla_flags, "_jaxlib_version", lambda: (0, 10, 2))
    assert _xla_flags.cpu_compiler_options() == {_xla_flags.PROGRAM_OPTION: False}
    monkeypatch.setattr(_xla_flags, "_jaxlib_version", lambda: (0, 9, 0))
    assert _xla_flags.cpu_compiler_options() == {}
    monkeypatch.setattr(_xla_flags, "_jaxlib_version", lambda: (0, 9, 1))
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert _xla_flags.cpu_compiler_options() == {}

    def program(x):
        return jnp.sin(x) @ jnp.cos(x).T + jnp.exp(x).sum(axis=0, keepdims=True)

    x = jnp.asarray(np.random.default_rng(0).normal(size=(16, 16)))
    flags = os.environ["XLA_FLAGS"]
    monkeypatch.setenv("XLA_FLAGS", "")
    fast = _programs.program_jit(program)
    np.testing.assert_allclose(fast(x), jax.jit(program)(x), rtol=1e-12, atol=1e-12)
    assert fast._jitted() is not fast._default  # compiled with the option
    assert os.environ["XLA_FLAGS"] == ""  # no flag of the process changed
    monkeypatch.setenv("XLA_FLAGS", flags)
    plain = _programs.program_jit(program)
    assert plain._jitted() is plain._default  # the user's XLA_FLAGS names the option
    monkeypatch.setattr(_programs, "cpu_compiler_options", lambda quick=False: {"xla_no_such_option": False})
    with pytest.raises(Exception, match="xla_no_such_option"):
        _programs.program_jit(program)(x)


def test_own_programs_run_inside_a_callers_jit_without_xla_flags(monkeypatch):
    """A library user without ``XLA_FLAGS`` (the suite's conftest sets them) calling
    heliojax's own programs inside a ``jax.jit`` of their own: JAX takes compiler
    options at the top level only, so the nested call must not pass them (it raised
    "`compiler_options` can only be passed to top-level `jax.jit`")."""
    monkeypatch.setenv("XLA_FLAGS", "")
    d = jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    for quick in (False, True):
        angles = _programs.program_jit(hj.direction_to_azimuth_elevation.__wrapped__, quick=quick)
        assert angles.compiler_options((d,))  # options at the top level
        np.testing.assert_allclose(jax.jit(angles)(d), angles(d), rtol=0, atol=1e-15)
        np.testing.assert_allclose(np.asarray(jax.jit(angles)(d))[:, 1], [np.pi / 2, 0.0], atol=1e-15)


def test_own_programs_take_a_callers_constants_inside_its_jit_without_xla_flags(monkeypatch):
    """The same with arrays that reach heliojax's program as constants of the caller's
    trace (closed over), not as tracers: JAX is tracing all the same, so
    the nested call must not pass compiler options either (it raised "`compiler_options`
    can only be passed to top-level `jax.jit`")."""
    monkeypatch.setenv("XLA_FLAGS", "")
    d = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    expected = np.array([np.pi / 2, 0.0])
    for quick in (False, True):
        angles = _programs.program_jit(hj.direction_to_azimuth_elevation.__wrapped__, quick=quick)
        np.testing.assert_allclose(jax.jit(lambda s: s * angles(d)[1])(2.0), 2.0 * expected, atol=1e-15)
    # the public function (a cached_jit), closed over
    np.testing.assert_allclose(
        jax.jit(lambda s: s * hj.direction_to_azimuth_elevation(d)[1])(2.0), 2.0 * expected, atol=1e-15
    )


def test_quick_programs_compile_at_level_0_on_small_inputs_only(monkeypatch):
    """``quick``: optimisation level 0 while the array arguments hold at most
    ``QUICK_MAX_ELEMENTS`` elements, XLA's default above; a user's ``XLA_FLAGS``
    naming the level wins; the results are those of the default level; a program
    that is not quick never gets the level."""
    from heliojax import _xla_flags

    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(_programs, "QUICK_MAX_ELEMENTS", 100)

    def program(x):
        return jnp.sin(x) @ jnp.cos(x).T + jnp.exp(x).sum(axis=0, keepdims=True)

    quick, plain = _programs.program_jit(program, quick=True), _programs.program_jit(program)
    small = jnp.asarray(np.random.default_rng(0).normal(size=(10, 10)))
    large = jnp.asarray(np.random.default_rng(1).normal(size=(11, 11)))
    level = _xla_flags.QUICK_OPTION
    assert quick.compiler_options((small,))[level] == 0
    assert level not in (quick.compiler_options((large,)) or {})
    assert level not in (plain.compiler_options((small,)) or {})
    for x in (small, large):
        np.testing.assert_allclose(quick(x), jax.jit(program)(x), rtol=1e-13, atol=1e-13)
    monkeypatch.setenv("XLA_FLAGS", f"--{level}=2")
    assert level not in (quick.compiler_options((small,)) or {})
    # the quick options reach XLA for small inputs only (an unknown one is refused)
    monkeypatch.setattr(_programs, "cpu_compiler_options", lambda quick: {"xla_no_such_option": 0} if quick else {})
    probe = _programs.program_jit(program, quick=True)
    np.testing.assert_allclose(probe(large), jax.jit(program)(large), rtol=1e-13, atol=1e-13)
    with pytest.raises(Exception, match="xla_no_such_option"):
        probe(small)


def test_a_quick_programs_executable_is_kept_under_its_options(program_dir, monkeypatch):
    """A quick program is kept (traced program and executable) like any other, and its
    level-0 executable and the default one of larger inputs are separate files."""
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(_programs, "QUICK_MAX_ELEMENTS", 4)
    square = _programs.cached_jit(_square, quick=True)
    np.testing.assert_array_equal(np.asarray(square(jnp.arange(3.0))), [0.0, 1.0, 4.0])
    np.testing.assert_array_equal(np.asarray(square(jnp.arange(5.0))), np.arange(5.0) ** 2)
    assert len(list(program_dir.glob("*.bin"))) == 2 and len(list(program_dir.glob("*.exe"))) == 2
    _programs._COMPILED.clear()
    monkeypatch.setattr(_programs, "_export", _no_export)
    monkeypatch.setattr(_programs, "_compile_noting_cache_hits", _no_export)
    np.testing.assert_array_equal(np.asarray(square(jnp.arange(3.0))), [0.0, 1.0, 4.0])


def test_clear_caches_drops_every_compiled_program_and_its_memory_maps(program_dir):
    """:func:`heliojax.clear_caches` drops heliojax's programs of this process and JAX's:
    the next call compiles again (the same result), and the memory mappings of the
    dropped executables are returned to the system (the reason to call it: Linux's
    per-process limit, see its docstring)."""
    power = _programs.cached_jit(_power)
    x = jnp.arange(4.0)
    first = np.asarray(power(x, 2))
    assert len(_programs._COMPILED) == 1

    def program(k):
        return jax.jit(lambda a: jnp.cumsum(jnp.sin(a * k)) @ jnp.outer(a, a) + jnp.linalg.norm(a) ** k)

    programs = [program(k) for k in range(20)]
    for p in programs:
        p(x).block_until_ready()
    before = hj.memory_map_count()
    hj.clear_caches()
    assert _programs._COMPILED == {} and all(p._cache_size() == 0 for p in programs)
    after = hj.memory_map_count()
    if sys.platform == "linux":
        assert before is not None and after is not None
        assert 0 < after[0] < before[0] < before[1] == after[1]
        assert before[0] - after[0] >= 20  # at least one mapping per dropped program
    np.testing.assert_array_equal(np.asarray(power(x, 2)), first)
    assert len(_programs._COMPILED) == 1
