"""Priors of a fit: extra residual rows that pull parameters toward a centre.

A prior contributes rows ``noise * (p - centre) / sigma`` (mrad) for the free
parameters, so that with measurement noise ``noise`` (mrad per component) the
cost is the negative log-posterior of a Gaussian prior ``N(centre, sigma^2)``.
``centre`` and ``sigma`` are models of the fitted model's structure (one
representation: the pytree); a parameter with ``sigma = inf`` has no prior.
"""

from __future__ import annotations

import abc
import typing
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._heliostat import known_values
from .._parameters import ParameterView, broadcast_model


class AbstractPrior(eqx.Module):
    """Prior rows of one heliostat's fit."""

    @abc.abstractmethod
    def rows(self, view: ParameterView, p: Float[Array, " P"], heliostat: typing.Any) -> Float[Array, " K"]:
        """Rows (mrad) at physical parameters ``p`` (vector order of ``view``);
        ``heliostat`` is this prior's per-heliostat slice (see :meth:`per_heliostat`)."""

    def per_heliostat(self, n: int) -> typing.Any:
        """The part of the prior that is batched over heliostats (a pytree with
        leading axis ``n``), handed to :meth:`rows` per heliostat."""
        del n
        return None

    def n_constrained(self, view: ParameterView, heliostat: typing.Any) -> Int[Array, ""]:
        """How many free parameters the prior constrains (0: none)."""
        del view, heliostat
        return jnp.zeros((), jnp.int32)

    def noise_mrad_of(self, heliostat: typing.Any) -> Float[Array, ""]:
        """The noise (mrad per component) the prior rows are scaled with (NaN: none)."""
        del heliostat
        return jnp.full((), jnp.nan)


@typing.final
class NoPrior(AbstractPrior):
    """No prior rows."""

    def rows(self, view, p, heliostat):
        del view, heliostat
        return jnp.zeros((0,), p.dtype)


@typing.final
class GaussianPrior(AbstractPrior):
    """Independent Gaussian priors ``N(centre, sigma^2)`` on the free parameters.

    Attributes:
        centre: model (batched over heliostats or not) holding the prior means.
        sigma: model of the same structure holding the prior standard deviations
            (physical units; ``inf`` = no prior on that parameter).
        noise_mrad: measurement noise per residual component (mrad): a scalar or
            ``(H,)``.

    Raises:
        ValueError: (where the values are known, not under ``jit``) a sigma that is not
            > 0 (NaN included) or a noise that is not finite and > 0, as
            :func:`gaussian_prior`; at a fit, a centre, sigma or noise batched over
            another number of heliostats than the fleet's.
    """

    centre: eqx.Module
    sigma: eqx.Module
    noise_mrad: Float[Array, "*h"]

    def __check_init__(self):
        # where the values are known (not under jit): a sigma of 0 or a NaN noise had made
        # every fitted heliostat DIVERGED, a NaN sigma meant no prior, a noise <= 0 a prior
        # of the wrong sign or none, without a word (gaussian_prior's rules)
        noise = known_values(self.noise_mrad)
        if noise is not None and not np.all(np.isfinite(noise) & (noise > 0)):
            bad = noise.reshape(-1)[~(np.isfinite(noise) & (noise > 0)).reshape(-1)][0]
            raise ValueError(f"GaussianPrior: noise_mrad must be finite and > 0 (mrad), got {bad}")
        sigma = known_values(ParameterView.of(self.sigma).to_vector(self.sigma))
        if sigma is not None and not np.all(sigma > 0):  # NaN too; inf: no prior
            raise ValueError(
                f"GaussianPrior: sigma must be > 0 (inf: no prior on that parameter), got {sigma[~(sigma > 0)][0]}"
            )

    def per_heliostat(self, n):
        def batch(name, m):
            leaves = [x for x in jax.tree.leaves(m) if eqx.is_array(x)]
            vector = ParameterView.of(m).to_vector(m)
            batched = bool(leaves) and vector.ndim == 2
            if batched and vector.shape[0] != n:  # had failed in the batching's scan, naming nothing
                raise ValueError(
                    f"GaussianPrior: {name} is batched over {vector.shape[0]} heliostats; the fleet has {n}"
                )
            return m if batched else broadcast_model(m, n)

        if jnp.ndim(self.noise_mrad) == 1 and jnp.shape(self.noise_mrad)[0] != n:
            raise ValueError(
                f"GaussianPrior: noise_mrad has {jnp.shape(self.noise_mrad)[0]} values (one per heliostat); "
                f"the fleet has {n} heliostats"
            )
        noise = jnp.broadcast_to(jnp.asarray(self.noise_mrad), (n,))
        return batch("centre", self.centre), batch("sigma", self.sigma), noise

    def n_constrained(self, view, heliostat):
        _, sigma, _ = heliostat
        s = view.to_vector(sigma)[jnp.asarray(view.free_index, dtype=jnp.int32)]
        return jnp.sum(jnp.isfinite(s)).astype(jnp.int32)

    def noise_mrad_of(self, heliostat):
        return heliostat[2]

    def rows(self, view, p, heliostat):
        centre, sigma, noise = heliostat
        idx = jnp.asarray(view.free_index, dtype=jnp.int32)
        c = view.to_vector(centre)[idx]
        s = view.to_vector(sigma)[idx]
        w = jnp.where(jnp.isfinite(s), 1.0 / s, 0.0)
        return (p[idx] - c) * w * noise


def gaussian_prior(model: eqx.Module, sigma: Mapping[str, float], noise_mrad: float = 0.5) -> GaussianPrior:
    """A :class:`GaussianPrior` centred on ``model`` with ``sigma`` given per parameter
    name (physical units; others none), e.g. ``{"gamma": 5e-3, "delta": 5e-3}``.

    Raises:
        ValueError: an unknown parameter name; a sigma that is not > 0 (NaN included;
            ``inf`` is no prior on that parameter); a ``noise_mrad`` that is not finite
            and > 0."""
    view = ParameterView.of(model)
    if not isinstance(sigma, Mapping):  # a list of pairs had been "prior on unknown parameters [('gamma', ...)]"
        raise TypeError(f"gaussian_prior: sigma must map parameter name -> sigma, not a {type(sigma).__name__}")
    for name, value in sigma.items():  # a string had failed in a comparison ('>' not supported)
        if (
            value is None
            or isinstance(value, (str, bytes))
            or np.ndim(value)
            or np.result_type(value).kind not in "iuf"
        ):
            raise TypeError(f"gaussian_prior: sigma[{name!r}] must be a number, got {value!r}"[:200])
    unknown = set(sigma) - set(view.names)
    if unknown:
        raise ValueError(f"prior on unknown parameters {sorted(unknown)}; known: {view.names}")
    vec = jnp.asarray([sigma.get(n, jnp.inf) for n in view.names], jnp.asarray(view.to_vector(model)).dtype)
    if vec.ndim and not all(s > 0 for s in sigma.values()):  # NaN too: a NaN sigma had meant no prior
        raise ValueError(f"prior sigmas must be > 0 (inf: no prior), got {dict(sigma)}")
    noise = None if isinstance(noise_mrad, jax.core.Tracer) else np.asarray(noise_mrad, float)  # pyright: ignore[reportAttributeAccessIssue]
    if noise is not None and not np.all((noise > 0) & np.isfinite(noise)):
        raise ValueError(f"gaussian_prior: noise_mrad must be finite and > 0, got {noise_mrad!r}")
    return GaussianPrior(centre=model, sigma=view.from_vector(model, vec), noise_mrad=jnp.asarray(noise_mrad))


__all__ = ["AbstractPrior", "GaussianPrior", "NoPrior", "gaussian_prior"]
