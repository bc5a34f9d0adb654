"""A shared zoo of test fleets, built once per test session (see conftest.py).

Every fleet is a :class:`heliojax.Fleet` built through the public API:

* ``stone``: 8 heliostats x 24 records, true Stone models, 0.2 mrad noise;
* ``actuator``: 8 x 24, true actuator models, 0.2 mrad noise;
* ``backlash``: 8 x 24 actuator fleet with a hidden 0.3 mrad backlash;
* ``padded``: ``stone`` padded to the next shape bucket (16 x 32);
* ``all_masked``: ``stone`` with every record masked out;
* ``embedded``: the embedded real PAINT subset (5 heliostats).

Tests that need a different size build their own with
:func:`heliojax.discovery.simulate_fleet`; sharing these keeps the number of
distinct shapes, and so of compiled programs, small.
"""

from __future__ import annotations

import functools
import typing

import equinox as eqx
import jax.numpy as jnp

import heliojax as hj
from heliojax.discovery import simulate_fleet
from heliojax.effects import make_effect

if typing.TYPE_CHECKING:
    from pathlib import Path

N_HELIOSTATS = 8
N_RECORDS = 24
NOISE_MRAD = 0.2


class Case(typing.NamedTuple):
    """A zoo entry: the fleet and the true models (None for real data)."""

    fleet: hj.Fleet
    truth: typing.Any


@functools.cache
def zoo(name: str) -> Case:
    """The zoo fleet called ``name`` (cached for the session)."""
    if name == "stone":
        return Case(*simulate_fleet(11, N_HELIOSTATS, N_RECORDS, base="stone8", noise_mrad=NOISE_MRAD))
    if name == "actuator":
        return Case(*simulate_fleet(12, N_HELIOSTATS, N_RECORDS, base="actuator", noise_mrad=NOISE_MRAD))
    if name == "backlash":
        effect = make_effect("backlash", hj.ActuatorModel.nominal(jnp.float64), backlash_1=3e-4, backlash_2=3e-4)
        return Case(
            *simulate_fleet(13, N_HELIOSTATS, N_RECORDS, effects=[effect], base="actuator", noise_mrad=NOISE_MRAD)
        )
    if name == "padded":
        base = zoo("stone")
        return Case(hj.pad_fleet(base.fleet, 16, 32), base.truth)
    if name == "all_masked":
        base = zoo("stone")
        return Case(eqx.tree_at(lambda f: f.mask, base.fleet, jnp.zeros_like(base.fleet.mask)), base.truth)
    if name == "embedded":
        return Case(hj.load_paint_directory(hj.default_data_dir()), None)
    raise KeyError(f"no zoo fleet {name!r}")


ZOO_NAMES = ("stone", "actuator", "backlash", "padded", "all_masked", "embedded")


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """``heliojax argv`` run in this process: ``(exit code, stdout, stderr)`` (argparse's
    usage errors, a SystemExit, give their code)."""
    from heliojax.cli._main import main

    try:
        rc = main(argv)
    except SystemExit as e:
        rc = int(e.code or 0)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def write_file(folder, name: str, content: str | bytes) -> str:
    """Write ``content`` (text as UTF-8, or bytes) to ``folder / name``; the path."""
    path = folder / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return str(path)


def unchecked_config(**fields):
    """``DiscoveryConfig(**fields)`` without the test run's runtime type checker (which
    rejects a wrong type first): the checks under test are the class's own, which a user
    meets."""
    from heliojax.discovery import DiscoveryConfig

    init = getattr(DiscoveryConfig.__init__, "__wrapped__", DiscoveryConfig.__init__)
    config = object.__new__(DiscoveryConfig)
    init(config, **fields)
    return config


def forged_results(fitted_h5: Path, tmp_path: Path, edit) -> Path:
    """A copy of ``fitted_h5`` in ``tmp_path`` changed by ``edit(file)`` (an open
    ``h5py.File``) with its row checksums recomputed (a forgery, or a tool that rewrites
    the file: the checksums alone do not find it)."""
    import shutil

    import h5py

    from heliojax._results import CHECKSUM_DATASET, _row_checksums

    results = tmp_path / "results.h5"
    shutil.copy(fitted_h5, results)
    with h5py.File(results, "r+") as f:
        edit(f)
        f[CHECKSUM_DATASET][...] = _row_checksums(f, len(f["heliostat_ids"]))
    return results
