"""Identifiability: how much of a candidate's signature the base model absorbs.

Under one data set's sampling (its poses, times, weather), a candidate effect
``c`` is a set of Jacobian columns ``B_h`` per heliostat (how the residuals
move per unit of the effect's parameters) and the current model is the
columns ``A_h`` (its free parameters). The part of ``B_h`` inside the column
space of ``A_h`` is *absorbed*: the current model's parameters can mimic it, so
the data cannot tell it from a recombination of the base parameters.

Pooled over heliostats, the absorbed fraction along a direction ``v`` of the
candidate's parameter space is::

    f(v) = 1 - sum_h |(I - P_h) B_h v|^2 / sum_h |B_h v|^2,     P_h = projector onto span(A_h)

The extremes of ``f`` are a generalised eigenproblem; the candidate's
absorbed fraction is the *smallest* one (its best-determined direction), so an
effect is identifiable as soon as one combination of its parameters is.

The limit is the collinearity diagnostic of Belsley, Kuh & Welsch
(*Regression Diagnostics*, 1980): a condition index above 30 marks strong
collinearity, where estimates are dominated by the near-dependence. A
direction that makes the angle ``phi`` with the current model's column space
(``cos^2 phi = f``) has, with its projection, a condition index
``cot(phi / 2) = sqrt((1 + cos phi) / (1 - cos phi))``; a condition index of 30
is ``cos phi = (30^2 - 1) / (30^2 + 1)``, i.e. ``f = 0.99557``.

Collinearity alone is not the whole story: an effect whose raw signature is
large (a 1 % pivot-radius error moves the joint angles by ~10 mrad, nearly all
of it a gear-ratio change the base absorbs) can leave a remainder the data
still measure well. So a candidate absorbed beyond the limit is *not
identifiable* only if, in addition, an effect of its **typical size**
(documented a priori per parameter, ``TYPICAL_SIZES`` of the effect classes:
the realistic sizes of the hidden-effect suites) would be measured from its
non-absorbed remainder no better than +-25 % at 2 standard errors: with
``lambda`` the noncentrality (information) of the typical-size remainder in its
best direction, pooled over heliostats with each heliostat's noise level,
``2 / sqrt(lambda) > 0.25``, i.e. ``lambda < 64``. Both conditions are
properties of the design (and the noise level), not of the candidate's fit to
the residuals, so they cost no multiple-testing budget. A not-identifiable
candidate is reported and never named.
"""

from __future__ import annotations

import numpy as np

CONDITION_INDEX_LIMIT = 30.0
"""Belsley-Kuh-Welsch strong-collinearity condition index."""

ABSORBED_LIMIT = ((CONDITION_INDEX_LIMIT**2 - 1.0) / (CONDITION_INDEX_LIMIT**2 + 1.0)) ** 2
"""Absorbed fraction above which a candidate is not identifiable (0.99557)."""

PRECISION_Z = 2.0
PRECISION_RELATIVE = 0.25
PRECISION_INFORMATION = (PRECISION_Z / PRECISION_RELATIVE) ** 2
"""Information (noncentrality) below which a typical-size remainder is measured
worse than +-25 % at 2 sigma (64)."""

RANK_RTOL = 1e-10
"""Relative singular-value tolerance for column spaces (numerical rank)."""


def column_basis(a: np.ndarray) -> np.ndarray:
    """Orthonormal basis ``(n, rank)`` of the column space of ``a`` (SVD, relative
    tolerance :data:`RANK_RTOL`)."""
    if a.size == 0 or a.shape[1] == 0:
        return np.zeros((a.shape[0], 0))
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    if s.size == 0 or s[0] == 0:
        return np.zeros((a.shape[0], 0))
    return u[:, s > s[0] * RANK_RTOL]


def column_bases(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`column_basis` of a stack ``(L, n, c)`` at once: ``(L, n, c)`` bases
    whose columns beyond each matrix's rank are zero, and the ranks ``(L,)``."""
    if a.shape[-1] == 0 or a.shape[-2] == 0:
        return np.zeros(a.shape), np.zeros(a.shape[0], np.int64)
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    keep = (s > s[:, :1] * RANK_RTOL) & (s[:, :1] > 0)
    return u * keep[:, None, :], keep.sum(axis=1)


def _gram(blocks) -> np.ndarray:
    """``sum_h X_h^T X_h`` of per-heliostat blocks: a list of ``(n_h, k)`` arrays or a
    zero-padded stack ``(S, R, k)`` (``(0, 0)`` for an empty list)."""
    if not isinstance(blocks, np.ndarray):
        if not len(blocks):
            return np.zeros((0, 0))
        blocks = np.concatenate([np.asarray(b, float) for b in blocks])
    rows = blocks.reshape(-1, blocks.shape[-1])
    return rows.T @ rows


def absorbed_fractions(b, b_res) -> np.ndarray:
    """Absorbed fractions of the candidate's directions, ascending (best first).

    Args:
        b: per heliostat, the candidate's columns ``B_h`` ``(n_h, k)``: a list, or a
            stack ``(S, R, k)`` whose rows beyond each heliostat's are zero.
        b_res: per heliostat, ``(I - P_h) B_h``, in the same form.

    Returns:
        ``(r,)`` fractions in [0, 1] over the ``r`` directions the data drive
        at all (empty when the candidate's columns are all zero: no driving data).
    """
    full = _gram(b)
    res = _gram(b_res)
    if full.shape[0] == 0:
        return np.zeros(0)
    ev, vec = np.linalg.eigh(full)
    if ev.max() <= 0:
        return np.zeros(0)
    keep = ev > ev.max() * RANK_RTOL
    w = vec[:, keep] / np.sqrt(ev[keep])
    kept = np.clip(np.linalg.eigvalsh(w.T @ res @ w), 0.0, 1.0)
    return np.sort(1.0 - kept)


def is_identifiable(fractions: np.ndarray, limit: float = ABSORBED_LIMIT) -> bool:
    """True when some direction is absorbed less than ``limit``."""
    return bool(fractions.size) and bool(fractions.min() <= limit)
