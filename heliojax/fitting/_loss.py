"""The loss of a fit: how record residuals enter the cost.

The cost of every fit is ``0.5 * sum(rows**2)`` over the rows the loss makes of
the records' tangent-plane residuals (mrad) plus the prior's rows. The loss acts
per record on the residual pair ``r = (r_1, r_2)``:

* :class:`LeastSquares` - rows ``r`` (Gaussian errors).
* :class:`Cauchy` - rows ``r * sqrt(log1p(z) / z)``, ``z = |r|^2 / c^2``, so that
  the record's cost is ``0.5 c^2 log(1 + |r|^2 / c^2)``: the Cauchy (Lorentzian)
  M-estimator, minimised by the same Levenberg-Marquardt solver (its Jacobian is
  exact, differentiated through the row). The scale ``c`` (mrad) is per heliostat
  (:func:`heliojax.fitting.fit_robust` estimates it from the data); ``c = inf`` is
  least squares exactly, so both share one compiled program.
"""

from __future__ import annotations

import abc
import typing

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._heliostat import known_values

CAUCHY_EFFICIENCY_FACTOR = 2.3849
"""Cauchy scale in units of the noise standard deviation for 95 % asymptotic
efficiency under Gaussian noise (Holland & Welsch 1977)."""


class AbstractLoss(eqx.Module):
    """Turns one record's residual pair (mrad) into the two rows whose half sum of
    squares is its cost (differentiated through by the fit)."""

    def per_heliostat(self, n: int) -> typing.Any:
        """The part of the loss batched over ``n`` heliostats (handed to
        :meth:`row` / :meth:`weight` per heliostat); default none."""
        del n
        return None

    @abc.abstractmethod
    def row(self, residual: Float[Array, " 2"], heliostat: typing.Any) -> Float[Array, " 2"]:
        """The record's rows at ``residual``."""

    @abc.abstractmethod
    def weight(self, residual: Float[Array, " 2"], heliostat: typing.Any) -> Float[Array, ""]:
        """The record's effective (IRLS) weight in ``[0, 1]`` at ``residual``."""

    @abc.abstractmethod
    def residual_of_row(self, row: Float[Array, " 2"], heliostat: typing.Any) -> Float[Array, " 2"]:
        """The residual pair (mrad) whose rows are ``row``: the inverse of :meth:`row`,
        so that a fit reads its residuals off the solver's last rows instead of
        evaluating the model a second time."""


@typing.final
class LeastSquares(AbstractLoss):
    """Plain least squares: the rows are the residuals."""

    def row(self, residual, heliostat):
        del heliostat
        return residual

    def weight(self, residual, heliostat):
        del heliostat
        return jnp.ones((), residual.dtype)

    def residual_of_row(self, row, heliostat):
        del heliostat
        return row


def _log1p_ratio(z: Float[Array, ""]) -> Float[Array, ""]:
    """``log1p(z) / z``, smooth through ``z = 0`` (value 1) and safe to differentiate."""
    small = z < 1e-8
    safe = jnp.where(small, 1.0, z)
    return jnp.where(small, 1.0 - 0.5 * z, jnp.log1p(safe) / safe)


@typing.final
class Cauchy(AbstractLoss):
    """The Cauchy (Lorentzian) robust loss with a per-heliostat scale.

    Attributes:
        scale_mrad: ``c`` in mrad, a scalar or ``(H,)``; ``inf`` = least squares.
    """

    scale_mrad: Float[Array, "*h"]

    def __check_init__(self):
        if isinstance(self.scale_mrad, (str, bytes)):  # "2" had been read as 2.0, failing inside the fit
            raise TypeError(f"Cauchy: scale_mrad must be a number or an array (mrad), got {self.scale_mrad!r}"[:200])
        if jnp.ndim(self.scale_mrad) > 1:
            raise ValueError(f"Cauchy: scale_mrad must be a scalar or (H,), got shape {jnp.shape(self.scale_mrad)}")
        # checked where the values are known (not under jit / vmap): a scale of 0 or
        # NaN had made every row of the heliostat NaN (z = |r|^2 / 0)
        c = known_values(self.scale_mrad)
        if c is None:
            return
        bad = ~(c > 0.0)  # NaN too; inf is least squares
        if bad.any():
            where = f" (heliostat {int(np.argmax(bad.reshape(-1)))})" if c.ndim else ""
            raise ValueError(
                f"Cauchy: scale_mrad must be > 0 (mrad; inf for least squares), got {float(c[bad][0])}{where}"
            )

    def per_heliostat(self, n):
        if jnp.ndim(self.scale_mrad) == 1 and jnp.shape(self.scale_mrad)[0] != n:  # had failed in broadcast_to
            raise ValueError(
                f"Cauchy: scale_mrad has {jnp.shape(self.scale_mrad)[0]} values (one per heliostat); "
                f"the fleet has {n} heliostats"
            )
        return jnp.broadcast_to(jnp.asarray(self.scale_mrad), (n,))

    def row(self, residual, heliostat):
        z = jnp.sum(residual**2) / heliostat**2
        return residual * jnp.sqrt(_log1p_ratio(z))

    def weight(self, residual, heliostat):
        z = jnp.sum(residual**2) / heliostat**2
        return 1.0 / (1.0 + z)

    def residual_of_row(self, row, heliostat):
        # |row|^2 = c^2 log1p(z), so z = expm1(|row|^2 / c^2) and r = row / sqrt(log1p(z) / z)
        z = jnp.expm1(jnp.sum(row**2) / heliostat**2)
        return row / jnp.sqrt(_log1p_ratio(z))


__all__ = ["CAUCHY_EFFICIENCY_FACTOR", "AbstractLoss", "Cauchy", "LeastSquares"]
