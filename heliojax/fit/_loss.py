"""The loss of a fit: how record residuals enter the cost.

The cost of every fit is ``0.5 * sum(rows**2)`` over the rows the loss makes of
the records' tangent-plane residuals (mrad) plus the prior's rows. The loss acts
per record on the residual pair ``r = (r_1, r_2)``:

* :class:`LeastSquares` - rows ``r`` (Gaussian errors).

Robust losses (a scale estimated per heliostat from its own data) plug in here:
they return the rows ``sqrt(rho(|r|^2 / s^2)) * s * r / |r|`` that a
Levenberg-Marquardt solver minimises like squares.
"""

from __future__ import annotations

import abc
import typing

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float


class AbstractLoss(eqx.Module):
    """Turns one record's residual pair (mrad) into the two rows whose half sum of
    squares is its cost (differentiated through by the fit)."""

    @abc.abstractmethod
    def row(self, residual: Float[Array, " 2"]) -> Float[Array, " 2"]:
        """The record's rows at ``residual``."""

    @abc.abstractmethod
    def weight(self, residual: Float[Array, " 2"]) -> Float[Array, ""]:
        """The record's effective weight in ``[0, 1]`` at ``residual`` (1 for least
        squares)."""


@typing.final
class LeastSquares(AbstractLoss):
    """Plain least squares: the rows are the residuals."""

    def row(self, residual):
        return residual

    def weight(self, residual):
        return jnp.ones((), residual.dtype)


__all__ = ["AbstractLoss", "LeastSquares"]
