"""The test suite's own guards are on: strict numerics and run-time type checks."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest

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
