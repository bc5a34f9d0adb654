"""The test suite's own guards are on: strict numerics and run-time type checks."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest
from helpers import zoo

import heliojax as hj


def test_float64_and_strict_promotion_are_on():
    assert jnp.ones(()).dtype == jnp.float64
    with pytest.raises(ValueError, match="rank"):
        _ = jnp.ones((2, 3)) + jnp.ones(3)
    with pytest.raises(jax.dtypes.TypePromotionError):
        _ = jnp.ones(3, jnp.float32) + jnp.ones(3, jnp.float64)


def test_annotated_shapes_are_checked_at_run_time():
    origin = np.array([50.9, 6.4, 87.0])
    assert hj.wgs84_to_enu(origin, origin).shape == (3,)
    with pytest.raises(jaxtyping.TypeCheckError):
        hj.wgs84_to_enu(np.zeros(2), origin)  # points must be (..., 3)


def test_fleet_metadata_does_not_key_compiled_programs():
    """Ids and the load report are static metadata outside the traced arrays: fitting
    a fleet that differs from another only in them reuses the compiled program."""
    fleet = zoo("stone").fleet
    renamed = dataclasses.replace(
        fleet,
        ids=tuple(f"X{i:03d}" for i in range(len(fleet.ids))),
        report=hj.LoadReport(source="elsewhere", records_loaded=1),
    )
    model0 = hj.StoneModel.nominal()
    compiles = []

    def listener(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    hj.fit(model0, fleet, max_steps=4)
    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        again = hj.fit(model0, renamed, max_steps=4)
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
    assert compiles == []
    assert again.model is not None


def test_every_module_class_is_abstract_or_final():
    """equinox's rule: a Module is abstract (named ``Abstract...``, never instantiated)
    or final (``typing.final``), so that no concrete class is overridden."""
    import importlib
    import inspect
    import pkgutil

    import equinox as eqx

    classes = set()
    for info in pkgutil.walk_packages(hj.__path__, "heliojax."):
        module = importlib.import_module(info.name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, eqx.Module) and cls.__module__.startswith("heliojax"):
                classes.add(cls)
    assert len(classes) > 40  # the walk found the package's modules
    loose = sorted(
        f"{c.__module__}.{c.__qualname__}"
        for c in classes
        if not (getattr(c, "__final__", False) or c.__name__.lstrip("_").startswith("Abstract"))
    )
    assert loose == []
