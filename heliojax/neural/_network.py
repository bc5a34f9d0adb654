"""Small self-normalising fully connected networks (Klambauer et al. 2017), as in
Pargmann et al.: SELU activations, LeCun-normal initialisation, linear output."""

from __future__ import annotations

import numbers
import typing
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

MAX_LAYER_WIDTH = 4096
"""Widest layer of a network (the paper's are 3-6 wide): a width of a billion had been
refused only by running out of memory."""

PAPER_HIDDEN: tuple[int, ...] = (6, 5, 4, 3)
"""Hidden layer widths of the paper's network (5 inputs, 6-5-4-3 hidden, 1 output)."""


@typing.final
class MLP(eqx.Module):
    """Fully connected network ``sizes[0] -> ... -> sizes[-1]``: SELU after every
    hidden layer, linear output.

    Weights are LeCun-normal (``jax.nn.initializers.lecun_normal``: truncated normal,
    variance ``1 / fan_in``), biases zero; with ``zero_output=True`` the output layer's
    weights and bias are zero, so the network is exactly 0 at initialisation (the
    residual variant).

    Attributes:
        weights: per layer ``(out, in)``.
        biases: per layer ``(out,)``.
    """

    weights: tuple[Float[Array, "_ _"], ...]  # layer sizes differ: no shared dimension names
    biases: tuple[Float[Array, " _"], ...]

    def __check_init__(self):
        if len(self.weights) != len(self.biases) or not self.weights:
            raise ValueError("MLP needs one bias per weight matrix and at least one layer")
        # layer shapes (static, known under jit too): a mismatch had failed at the first
        # call with a dot_general or broadcasting error naming no layer
        previous = None
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            ws, bs = tuple(jnp.shape(w)), tuple(jnp.shape(b))
            if len(ws) < 2:
                raise ValueError(f"MLP: weights[{i}] has shape {ws}; expected (..., out, in)")
            if bs != ws[:-1]:
                raise ValueError(f"MLP: biases[{i}] has shape {bs}; expected {ws[:-1]} (weights[{i}] {ws})")
            if previous is not None and ws[-1] != previous[-2]:
                raise ValueError(
                    f"MLP: weights[{i}] takes {ws[-1]} inputs but layer {i - 1} gives {previous[-2]} "
                    f"(weights[{i - 1}] {previous}, weights[{i}] {ws})"
                )
            previous = ws

    @classmethod
    def init(cls, key: PRNGKeyArray, sizes: Sequence[int], *, zero_output: bool = False, dtype=jnp.float32) -> MLP:
        """A freshly initialised network with layer widths ``sizes`` (inputs first)."""
        given = tuple(sizes)
        if len(given) < 2 or not all(
            isinstance(s, numbers.Integral) and not isinstance(s, bool) and 1 <= s <= MAX_LAYER_WIDTH for s in given
        ):  # a width of 2.7 had been cut to 2, True read as 1
            raise ValueError(f"MLP sizes must be >= 2 whole numbers in [1, {MAX_LAYER_WIDTH}], got {given!r}")
        sizes = tuple(int(s) for s in given)
        init = jax.nn.initializers.lecun_normal(in_axis=1, out_axis=0)
        keys = jax.random.split(key, len(sizes) - 1)
        ws, bs = [], []
        for i, (k, n_in, n_out) in enumerate(zip(keys, sizes[:-1], sizes[1:])):
            last = i == len(sizes) - 2
            if last and zero_output:
                w = jnp.zeros((n_out, n_in), dtype)
            else:
                w = init(k, (n_out, n_in), dtype)
            ws.append(w)
            bs.append(jnp.zeros((n_out,), dtype))
        return cls(weights=tuple(ws), biases=tuple(bs))

    @property
    def sizes(self) -> tuple[int, ...]:
        return (self.weights[0].shape[-1],) + tuple(w.shape[-2] for w in self.weights)

    def __call__(self, x: Float[Array, " i"]) -> Float[Array, " o"]:
        """One input vector -> one output vector (vmap for batches)."""
        x = jnp.asarray(x, self.weights[0].dtype)
        if x.shape != self.weights[0].shape[-1:]:
            raise ValueError(f"MLP: input of shape {x.shape}; the network takes {self.weights[0].shape[-1:]}")
        for w, b in zip(self.weights[:-1], self.biases[:-1]):
            x = jax.nn.selu(w @ x + b)
        return self.weights[-1] @ x + self.biases[-1]


def init_networks(
    key: PRNGKeyArray, shape: tuple[int, ...], sizes: Sequence[int], *, zero_output: bool = False, dtype=jnp.float32
) -> MLP:
    """Networks stacked along leading axes ``shape`` (one independent initialisation
    each; the key of entry ``i`` of a 1-D stack is ``jax.random.fold_in(key, i)``)."""
    if not all(isinstance(s, numbers.Integral) and not isinstance(s, bool) and s >= 1 for s in shape):
        raise ValueError(f"init_networks: shape must hold whole numbers >= 1, got {tuple(shape)!r}")
    n = 1
    for s in shape:
        n *= int(s)
    keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(n))
    nets = eqx.filter_vmap(lambda k: MLP.init(k, sizes, zero_output=zero_output, dtype=dtype))(keys)
    return jax.tree_util.tree_map(lambda x: x.reshape(tuple(shape) + x.shape[1:]), nets)


__all__ = ["MLP", "PAPER_HIDDEN", "init_networks"]
