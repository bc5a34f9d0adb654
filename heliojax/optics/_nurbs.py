"""NURBS facet surfaces: evaluation, ideal facets and fits to deflectometry.

Each facet is a tensor-product NURBS patch of degree ``p`` over ``[0, 1]^2``
with clamped uniform knots, control points ``(n_u, n_v, 3)`` in facet-local
coordinates (metres, surface frame orientation) and weights ``(n_u, n_v)``; the
facet sits at ``translation`` in the surface frame. ``u`` runs along the
facet's ``canting_e`` (east) edge, ``v`` along ``canting_n``; the normal is
``normalize(S_u x S_v)`` (``+z`` side).

Batched over facets and heliostats by leading axes; facets of heliostats with
fewer facets are padded and masked (``facet_mask``), so nothing requires equal
counts.

Fitting (:func:`fit_nurbs`): control points keep ``x, y`` on the Greville
abscissae of the facet's bounding box — for a clamped B-spline this makes
``x(u), y(v)`` exactly linear — and the heights ``z`` are the solution of the
linear least-squares problem

    mean_k [(z_x(k) - g_x(k))^2 + (z_y(k) - g_y(k))^2]
      + height_weight * mean_k (z(k) - z_k)^2 + smoothing * |D2 z|^2

with the measured slopes ``g = (-n_x / n_z, -n_y / n_z)`` (the normals are what
flux depends on; the weak height term fixes the constant), solved by normal
equations per facet (``lax.map``, so memory stays ``O(points x control points)``
for one facet at a time).
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._surfaces import Deflectometry, FacetLayout, SurfacePoints


def clamped_knots(n_ctrl: int, degree: int) -> np.ndarray:
    """Clamped uniform knot vector on ``[0, 1]`` (``n_ctrl + degree + 1`` knots)."""
    if n_ctrl <= degree:
        raise ValueError(f"need more control points ({n_ctrl}) than the degree ({degree})")
    inner = np.linspace(0.0, 1.0, n_ctrl - degree + 1)
    return np.concatenate([np.zeros(degree), inner, np.ones(degree)])


def greville(n_ctrl: int, degree: int) -> np.ndarray:
    """Greville abscissae (in ``[0, 1]``) of the clamped uniform knots."""
    k = clamped_knots(n_ctrl, degree)
    return np.array([k[i + 1 : i + degree + 1].mean() for i in range(n_ctrl)])


def bspline_basis(
    t: Float[ArrayLike, "..."], n_ctrl: int, degree: int
) -> tuple[Float[Array, "... n"], Float[Array, "... n"]]:
    """B-spline basis values and first derivatives at ``t`` (clamped uniform knots).

    Cox-de Boor recursion, vectorised over ``t``; the right end ``t = 1`` belongs
    to the last span. Differentiable in ``t``.

    Returns:
        ``(N, dN/dt)``, each ``(..., n_ctrl)``.
    """
    t = jnp.clip(jnp.asarray(t), 0.0, 1.0)[..., None]
    knots = np.asarray(clamped_knots(n_ctrl, degree), dtype=t.dtype)
    lead = (1,) * (t.ndim - 1)
    lo, hi = knots[:-1].reshape(lead + (-1,)), knots[1:].reshape(lead + (-1,))
    n = ((t >= lo) & (t < hi)).astype(t.dtype)
    last = len(knots) - degree - 2
    at_end = (t[..., 0] >= 1.0).astype(t.dtype)
    n = n.at[..., last].set(jnp.maximum(n[..., last], at_end))
    prev = n
    for d in range(1, degree + 1):
        m = len(knots) - 1 - d
        k0 = knots[:m]
        kd = knots[d : d + m]
        k1 = knots[1 : 1 + m]
        kd1 = knots[d + 1 : d + 1 + m]
        inv_a = np.where(kd - k0 > 0, 1.0 / np.where(kd - k0 > 0, kd - k0, 1.0), 0.0)
        inv_b = np.where(kd1 - k1 > 0, 1.0 / np.where(kd1 - k1 > 0, kd1 - k1, 1.0), 0.0)
        k0, kd1, inv_a, inv_b = (np.reshape(x, lead + (-1,)) for x in (k0, kd1, inv_a, inv_b))
        new = (t - k0) * inv_a * prev[..., :m] + (kd1 - t) * inv_b * prev[..., 1 : m + 1]
        if d == degree:
            deriv = d * (inv_a * prev[..., :m] - inv_b * prev[..., 1 : m + 1])
        prev = new
    if degree == 0:
        deriv = jnp.zeros_like(prev)
    return prev, deriv  # pyright: ignore[reportPossiblyUnbound, reportReturnType]


@typing.final
class NurbsFacets(eqx.Module):
    """NURBS facets of one heliostat (``(f, ...)``) or a batch (``(*b, f, ...)``).

    Attributes:
        control_points: ``(*b, f, n_u, n_v, 3)`` facet-local, m.
        weights: ``(*b, f, n_u, n_v)`` positive NURBS weights (1 = B-spline).
        translations: ``(*b, f, 3)`` facet centres in the surface frame, m.
        facet_mask: ``(*b, f)`` True for real facets.
        degree: polynomial degree (static).
    """

    control_points: Float[Array, "*b f nu nv 3"]
    weights: Float[Array, "*b f nu nv"]
    translations: Float[Array, "*b f 3"]
    facet_mask: Bool[Array, "*b f"]
    degree: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        cp = jnp.shape(self.control_points)
        if cp[-1:] != (3,) or jnp.shape(self.weights) != cp[:-1]:
            raise ValueError(f"control points {cp} and weights {jnp.shape(self.weights)} disagree")
        if cp[-3] <= self.degree or cp[-2] <= self.degree:
            raise ValueError(f"need more than degree={self.degree} control points per direction, got {cp[-3:-1]}")

    @property
    def n_ctrl(self) -> tuple[int, int]:
        return self.control_points.shape[-3], self.control_points.shape[-2]

    @classmethod
    def ideal(cls, layout: FacetLayout, n_ctrl: tuple[int, int] = (6, 6), degree: int = 3) -> NurbsFacets:
        """Flat canted facets of ``layout`` as exact NURBS patches: control point
        ``(i, j)`` is ``g_i canting_e + g_j canting_n`` with ``g`` the Greville
        abscissae mapped to ``[-1, 1]`` (linear precision makes the patch the flat
        parallelogram)."""
        dt = layout.translations.dtype
        gu = jnp.asarray(2.0 * greville(n_ctrl[0], degree) - 1.0, dt)
        gv = jnp.asarray(2.0 * greville(n_ctrl[1], degree) - 1.0, dt)
        lead = (1,) * (layout.canting_e.ndim - 1)  # the batch and facet axes
        cp = (
            gu.reshape(lead + (-1, 1, 1)) * layout.canting_e[..., :, None, None, :]
            + gv.reshape(lead + (1, -1, 1)) * layout.canting_n[..., :, None, None, :]
        )
        return cls(
            control_points=cp,
            weights=jnp.ones(cp.shape[:-1], dt),
            translations=layout.translations,
            facet_mask=layout.mask,
            degree=degree,
        )

    def evaluate_at(
        self, u: Float[ArrayLike, " m"], v: Float[ArrayLike, " k"]
    ) -> tuple[Float[Array, "*b f m k 3"], Float[Array, "*b f m k 3"], Float[Array, "*b f m k 3"]]:
        """Points ``S`` (facet-local, without translation) and the partial derivatives
        ``S_u``, ``S_v`` on the tensor grid ``u x v``."""
        nu, nv = self.n_ctrl
        bu, dbu = bspline_basis(jnp.asarray(u, self.control_points.dtype), nu, self.degree)
        bv, dbv = bspline_basis(jnp.asarray(v, self.control_points.dtype), nv, self.degree)
        w = self.weights
        pw = self.control_points * w[..., None]

        def contract(a, b, x):
            return jnp.einsum("mi,...ijc,kj->...mkc", a, x, b)

        a = contract(bu, bv, pw)
        au = contract(dbu, bv, pw)
        av = contract(bu, dbv, pw)
        ww = contract(bu, bv, w[..., None])
        wu = contract(dbu, bv, w[..., None])
        wv = contract(bu, dbv, w[..., None])
        s = a / ww
        su = (au - wu * s) / ww
        sv = (av - wv * s) / ww
        return s, su, sv

    def evaluate(self, resolution: tuple[int, int] = (32, 32)) -> SurfacePoints:
        """Sample every facet on a cell-centred ``resolution = (m, k)`` parameter grid.

        Points and normals are taken at the cell centres; a point's area is that of
        its cell's image, ``|d1 x d2| / 2`` with ``d1, d2`` the diagonals between the
        mapped cell corners (exact for flat facets however the control points are
        spread, e.g. ARTIST's uniform ones, where the midpoint rule
        ``|S_u x S_v| / (m k)`` converges only as ``1 / m``); padded facets get area 0.

        Returns:
            :class:`SurfacePoints` ``(*b, f * m * k)`` in the surface frame.
        """
        return _evaluate_grid(self, int(resolution[0]), int(resolution[1]))

    def normals_at(self, xy: Float[ArrayLike, "*b f p 2"]) -> Float[Array, "*b f p 3"]:
        """Unit normals at facet-local ``(x, y)`` points, for height-field patches
        built by :func:`fit_nurbs` or :meth:`ideal` (``x, y`` linear in ``u, v``)."""
        return _normals_at(self, xy)


@eqx.filter_jit
def _evaluate_grid(self: NurbsFacets, m: int, k: int) -> SurfacePoints:
    """:meth:`NurbsFacets.evaluate`, compiled once per shape and resolution."""
    u = (np.arange(m) + 0.5) / m
    v = (np.arange(k) + 0.5) / k
    s, su, sv = self.evaluate_at(u, v)
    c = jnp.cross(su, sv)
    normals = c / jnp.linalg.norm(c, axis=-1, keepdims=True)
    corners, _, _ = self.evaluate_at(np.linspace(0.0, 1.0, m + 1), np.linspace(0.0, 1.0, k + 1))
    d1 = corners[..., 1:, 1:, :] - corners[..., :-1, :-1, :]
    d2 = corners[..., :-1, 1:, :] - corners[..., 1:, :-1, :]
    cell = 0.5 * jnp.linalg.norm(jnp.cross(d1, d2), axis=-1)
    areas = cell * self.facet_mask[..., None, None].astype(cell.dtype)
    pts = s + self.translations[..., :, None, None, :]
    lead = pts.shape[:-4]
    return SurfacePoints(
        points=pts.reshape(lead + (-1, 3)),
        normals=normals.reshape(lead + (-1, 3)),
        areas=areas.reshape(lead + (-1,)),
    )


@eqx.filter_jit
def _normals_at(self: NurbsFacets, xy) -> Array:
    """:meth:`NurbsFacets.normals_at`, compiled."""
    xy = jnp.asarray(xy, self.control_points.dtype)
    cp = self.control_points
    x0 = cp[..., 0, 0, 0]
    x1 = cp[..., -1, 0, 0]
    y0 = cp[..., 0, 0, 1]
    y1 = cp[..., 0, -1, 1]
    u = (xy[..., 0] - x0[..., None]) / (x1 - x0)[..., None]
    v = (xy[..., 1] - y0[..., None]) / (y1 - y0)[..., None]
    nu, nv = self.n_ctrl

    def one(cpf, wf, uf, vf):
        bu, dbu = bspline_basis(uf, nu, self.degree)
        bv, dbv = bspline_basis(vf, nv, self.degree)
        pw = cpf * wf[..., None]

        def c(a, b, x):
            return jnp.einsum("pi,ijc,pj->pc", a, x, b)

        a, au, av = c(bu, bv, pw), c(dbu, bv, pw), c(bu, dbv, pw)
        ww, wu, wv = c(bu, bv, wf[..., None]), c(dbu, bv, wf[..., None]), c(bu, dbv, wf[..., None])
        s = a / ww
        n = jnp.cross((au - wu * s) / ww, (av - wv * s) / ww)
        return n / jnp.linalg.norm(n, axis=-1, keepdims=True)

    lead = cp.shape[:-3]
    flat = lambda x, k: x.reshape((-1,) + x.shape[len(lead) :])  # noqa: E731
    out = jax.vmap(one)(flat(cp, 0), flat(self.weights, 0), flat(u, 0), flat(v, 0))
    return out.reshape(lead + out.shape[1:])


def _second_difference(n_u: int, n_v: int) -> np.ndarray:
    """Rows: second differences of an ``(n_u, n_v)`` grid along both directions."""
    rows = []
    for i in range(n_u):
        for j in range(n_v):
            if 0 < i < n_u - 1:
                r = np.zeros((n_u, n_v))
                r[i - 1, j], r[i, j], r[i + 1, j] = 1.0, -2.0, 1.0
                rows.append(r.ravel())
            if 0 < j < n_v - 1:
                r = np.zeros((n_u, n_v))
                r[i, j - 1], r[i, j], r[i, j + 1] = 1.0, -2.0, 1.0
                rows.append(r.ravel())
    return np.asarray(rows)


def fit_nurbs(
    deflectometry: Deflectometry,
    translations: Float[ArrayLike, "*b f 3"],
    n_ctrl: tuple[int, int] = (8, 8),
    degree: int = 3,
    height_weight: float = 1.0,
    smoothing: float = 1e-8,
) -> NurbsFacets:
    """Fit B-spline height-field patches (NURBS with unit weights) to deflectometry.

    Batched over facets and heliostats (``(*b, f, p)`` padded/masked input); each
    facet is one linear least-squares solve (see the module docstring).

    Args:
        deflectometry: facet-local points and normals with mask.
        translations: ``(*b, f, 3)`` facet centres in the surface frame, m (from the
            heliostat properties).
        n_ctrl: control points per direction.
        degree: spline degree.
        height_weight: weight of the mean squared height residual (m^-2, relative
            to slopes in rad^2).
        smoothing: weight of the squared second differences of the control heights.

    Returns:
        :class:`NurbsFacets` with the facets' masks (a facet without points is masked out).
    """
    nu, nv = n_ctrl
    dt = deflectometry.points.dtype
    lead = deflectometry.mask.shape[:-1]
    p = deflectometry.mask.shape[-1]
    pts = deflectometry.points.reshape((-1, p, 3))
    nrm = deflectometry.normals.reshape((-1, p, 3))
    msk = deflectometry.mask.reshape((-1, p))
    gu = jnp.asarray(greville(nu, degree), dt)
    gv = jnp.asarray(greville(nv, degree), dt)
    d2 = jnp.asarray(_second_difference(nu, nv), dt)

    def one(args):
        x, n, m = args
        w = m.astype(dt)
        cnt = jnp.maximum(jnp.sum(w), 1.0)
        big = jnp.asarray(1e30, dt)
        x0 = jnp.min(jnp.where(m, x[:, 0], big))
        x1 = jnp.max(jnp.where(m, x[:, 0], -big))
        y0 = jnp.min(jnp.where(m, x[:, 1], big))
        y1 = jnp.max(jnp.where(m, x[:, 1], -big))
        ok = jnp.sum(w) > 0
        x0, x1 = jnp.where(ok, x0, -1.0), jnp.where(ok, x1, 1.0)
        y0, y1 = jnp.where(ok, y0, -1.0), jnp.where(ok, y1, 1.0)
        lx, ly = x1 - x0, y1 - y0
        u = (x[:, 0] - x0) / lx
        v = (x[:, 1] - y0) / ly
        bu, dbu = bspline_basis(u, nu, degree)
        bv, dbv = bspline_basis(v, nv, degree)
        b = (bu[:, :, None] * bv[:, None, :]).reshape(p, -1)
        dx = (dbu[:, :, None] * bv[:, None, :]).reshape(p, -1) / lx
        dy = (bu[:, :, None] * dbv[:, None, :]).reshape(p, -1) / ly
        nz = jnp.where(m, n[:, 2], 1.0)
        gx = jnp.where(m, -n[:, 0] / nz, 0.0)
        gy = jnp.where(m, -n[:, 1] / nz, 0.0)
        z = jnp.where(m, x[:, 2], 0.0)
        wn = w / cnt
        wn = wn[None, :]
        lhs = (dx.T * wn) @ dx + (dy.T * wn) @ dy + height_weight * (b.T * wn) @ b + smoothing * d2.T @ d2
        rhs = (dx.T * wn) @ gx + (dy.T * wn) @ gy + height_weight * (b.T * wn) @ z
        lhs = lhs + 1e-12 * jnp.trace(lhs) / lhs.shape[0] * jnp.eye(lhs.shape[0], dtype=dt)
        zc = jnp.linalg.solve(lhs, rhs).reshape(nu, nv)
        cx = x0 + gu * lx
        cy = y0 + gv * ly
        cp = jnp.stack([jnp.broadcast_to(cx[:, None], (nu, nv)), jnp.broadcast_to(cy[None, :], (nu, nv)), zc], axis=-1)
        return cp, ok

    cp, ok = jax.lax.map(one, (pts, nrm, msk))
    cp = cp.reshape(lead + (nu, nv, 3))
    ok = ok.reshape(lead)
    return NurbsFacets(
        control_points=cp,
        weights=jnp.ones(cp.shape[:-1], dt),
        translations=jnp.broadcast_to(jnp.asarray(translations, dt), lead + (3,)),
        facet_mask=ok,
        degree=degree,
    )


def normal_errors_mrad(facets: NurbsFacets, deflectometry: Deflectometry) -> Float[Array, "*b f p"]:
    """Angle (mrad) between the patches' normals and the measured normals at the
    measured ``(x, y)`` (0 where masked)."""
    n = facets.normals_at(deflectometry.points[..., :2])
    m = deflectometry.normals
    cross = jnp.linalg.norm(jnp.cross(n, m), axis=-1)
    ang = jnp.arctan2(cross, jnp.sum(n * m, axis=-1)) * 1e3
    return jnp.where(deflectometry.mask, ang, 0.0)


def rms_normal_error_mrad(facets: NurbsFacets, deflectometry: Deflectometry) -> Float[Array, ""]:
    """RMS over all measured points of :func:`normal_errors_mrad`."""
    e = normal_errors_mrad(facets, deflectometry)
    return jnp.sqrt(jnp.sum(e**2) / jnp.maximum(jnp.sum(deflectometry.mask), 1).astype(e.dtype))


__all__ = [
    "NurbsFacets",
    "bspline_basis",
    "clamped_knots",
    "fit_nurbs",
    "greville",
    "normal_errors_mrad",
    "rms_normal_error_mrad",
]
