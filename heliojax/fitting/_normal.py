"""The Levenberg-Marquardt step by Cholesky of the normal equations, with every
product written as multiply-and-reduce.

A heliostat's damped step solves ``min |A x - b|`` for an ``(R + F) x F`` matrix ``A``
(``R`` residual rows, ``F`` <= a few dozen free parameters). ``lineax.Normal(
lineax.Cholesky())`` forms ``A^T A`` and ``A^T b`` with ``dot``; vmapped over 100,000
heliostats these become batched GEMM kernels of tiny float64 matrices, which on an
H200 ran ~200x slower than the arithmetic needs (README, Benchmarks). Here the
products are elementwise multiplications summed over an axis: XLA fuses them into
reduction kernels on every backend. The arithmetic is the same; only the summation
order differs.
"""

from __future__ import annotations

import dataclasses
import math
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy as jsp
import lineax as lx
from jaxtyping import Array, Float

__all__ = ["NormalCholesky"]


def _ravel(tree: typing.Any) -> Float[Array, " n"]:
    return jnp.concatenate([jnp.ravel(leaf) for leaf in jax.tree.leaves(tree)])


def _unravel(vector: Float[Array, " n"], structure: typing.Any) -> typing.Any:
    leaves, treedef = jax.tree.flatten(structure)
    out, start = [], 0
    for leaf in leaves:
        size = math.prod(leaf.shape)
        out.append(vector[start : start + size].reshape(leaf.shape).astype(leaf.dtype))
        start += size
    return jax.tree.unflatten(treedef, out)


@typing.final
class _NormalState(eqx.Module):
    matrix: Float[Array, "R F"]
    factor: Float[Array, "F F"]  # upper Cholesky factor of matrix^T matrix
    transposed: bool = eqx.field(static=True)
    in_structure: typing.Any = eqx.field(static=True)
    out_structure: typing.Any = eqx.field(static=True)


@typing.final
class NormalCholesky(lx.AbstractLinearSolver[_NormalState]):
    """Least-squares solve of ``A x = b`` (``A`` tall, full column rank) by Cholesky of
    ``A^T A``: ``x = (A^T A)^-1 A^T b``. The transposed (wide) system gets the
    minimum-norm solution ``A (A^T A)^-1 c``.

    Use it as ``optimistix.LevenbergMarquardt(..., linear_solver=NormalCholesky())``
    (:func:`heliojax.fitting.default_solver` does so on accelerators). The damping
    keeps ``A^T A`` positive definite; an undamped rank-deficient ``A`` gives NaN, as
    ``lineax.Normal(lineax.Cholesky())`` does.
    """

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, typing.Any]) -> _NormalState:
        del options
        matrix = operator.as_matrix()
        if matrix.shape[0] < matrix.shape[1]:
            raise ValueError(f"NormalCholesky needs a tall operator, got a {matrix.shape[0]} x {matrix.shape[1]} one")
        gram = jnp.sum(matrix[:, :, None] * matrix[:, None, :], axis=0)
        factor, _ = jsp.linalg.cho_factor(gram, lower=False)
        return _NormalState(matrix, factor, False, operator.in_structure(), operator.out_structure())

    def compute(
        self, state: _NormalState, vector: typing.Any, options: dict[str, typing.Any]
    ) -> tuple[typing.Any, lx.RESULTS, dict[str, typing.Any]]:
        del options
        b = _ravel(vector)
        if state.transposed:  # A^T x = b, minimum norm: x = A (A^T A)^-1 b
            z = jsp.linalg.cho_solve((state.factor, False), b)
            x = jnp.sum(state.matrix * z[None, :], axis=1)
            return _unravel(x, state.out_structure), lx.RESULTS.successful, {}
        atb = jnp.sum(state.matrix * b[:, None], axis=0)
        x = jsp.linalg.cho_solve((state.factor, False), atb)
        return _unravel(x, state.in_structure), lx.RESULTS.successful, {}

    def transpose(self, state: _NormalState, options: dict[str, typing.Any]) -> tuple[_NormalState, dict]:
        del options
        return dataclasses.replace(state, transposed=not state.transposed), {}

    def conj(self, state: _NormalState, options: dict[str, typing.Any]) -> tuple[_NormalState, dict]:
        del options
        return state, {}  # real matrices only

    def assume_full_rank(self) -> bool:
        return True
