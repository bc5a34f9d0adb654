"""Mirror surfaces: sampled points, ideal canted facets and PAINT deflectometry.

Everything here lives in the heliostat's *surface frame* (mirror face up,
normal ``+z``, ``x`` east, ``y`` north at the reference pose; see
:mod:`heliojax._geometry`). A pose's ``rotation`` and ``centre`` take it to ENU.

* :class:`SurfacePoints` is what the ray tracer consumes: sample points, unit
  normals and the mirror area each point stands for (``0`` marks padding).
  Batched with a leading heliostat axis; heliostats with fewer points are
  padded (:func:`stack_surfaces`), so no equal-count requirement exists.
* :class:`FacetLayout` is the facet geometry of a PAINT heliostat-properties
  file: per facet the centre ``translation_vector`` and the half-edge vectors
  ``canting_e`` / ``canting_n`` (their directions carry the canting, the facet
  normal is ``normalize(canting_e x canting_n)``).
* :class:`Deflectometry` holds a PAINT deflectometry HDF5 file (groups
  ``facet1..facetN`` with ``surface_points`` / ``surface_normals`` ``[N, 3]``,
  facet-local with the canting built in), padded to equal counts with a mask.
"""

from __future__ import annotations

import os
import typing
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._errors import DataError
from .._heliostat import known_values
from .._limits import count_problem
from ..paint import read_deflectometry_facets, read_facets, write_deflectometry
from ..paint._properties import MIN_CANTING_SINE, MIN_FACET_HALF_SIZE_M


@typing.final
class SurfacePoints(eqx.Module):
    """Sampled mirror in the surface frame.

    Attributes:
        points: ``(*b, p, 3)`` m, surface frame.
        normals: ``(*b, p, 3)`` unit normals (surface frame).
        areas: ``(*b, p)`` m^2 of mirror each point represents; ``0`` = padding.
    """

    points: Float[Array, "*b p 3"]
    normals: Float[Array, "*b p 3"]
    areas: Float[Array, "*b p"]

    def __check_init__(self):
        ps, ns, as_ = jnp.shape(self.points), jnp.shape(self.normals), jnp.shape(self.areas)
        if ps != ns or ps[-1:] != (3,) or ps[:-1] != as_:
            raise ValueError(f"SurfacePoints shapes disagree: points {ps}, normals {ns}, areas {as_}")
        # values, where known (not under jit / vmap): a negative or NaN area had traced
        # negative or NaN flux, a NaN or zero normal lost its point's rays without a word
        points, normals, areas = (known_values(x) for x in (self.points, self.normals, self.areas))
        if points is None or normals is None or areas is None:
            return
        mirror = areas > 0.0  # padding (area 0) carries no power: its normal is not read
        problems = (
            ("areas", ~(np.isfinite(areas) & (areas >= 0.0)), "m^2 of mirror, finite and >= 0 (0: padding)"),
            ("points", ~np.isfinite(points).all(axis=-1), "finite positions (m)"),
            (
                "normals",
                mirror & ~(np.isfinite(normals).all(axis=-1) & (np.abs(normals).sum(axis=-1) > 0.0)),
                "finite, non-zero normals where the area is > 0",
            ),
        )
        for name, bad, expected in problems:
            if bad.any():
                at = tuple(int(k) for k in np.argwhere(bad)[0])
                value = (areas if name == "areas" else points if name == "points" else normals)[at]
                raise ValueError(
                    f"SurfacePoints: {name}[{', '.join(map(str, at))}] is {np.round(value, 6).tolist()} "
                    f"({int(bad.sum())} bad); expected {expected}"
                )

    @property
    def n_points(self) -> int:
        return self.areas.shape[-1]

    def total_area(self) -> Float[Array, "*b"]:
        """Mirror area in m^2 (sum of the point areas)."""
        return jnp.sum(self.areas, axis=-1)

    def pad_to(self, n: int) -> SurfacePoints:
        """Pad (with zero-area points at the origin, normal ``+z``) to ``n`` points."""
        extra = n - self.n_points
        if extra < 0:
            raise ValueError(f"cannot pad {self.n_points} points to {n}")
        if extra == 0:
            return self
        lead = self.areas.shape[:-1]
        zeros3 = jnp.zeros(lead + (extra, 3), self.points.dtype)
        up = zeros3.at[..., 2].set(1.0)
        return SurfacePoints(
            points=jnp.concatenate([self.points, zeros3], axis=-2),
            normals=jnp.concatenate([self.normals, up], axis=-2),
            areas=jnp.concatenate([self.areas, jnp.zeros(lead + (extra,), self.areas.dtype)], axis=-1),
        )


def _check_some(function: str, name: str, items: typing.Any, kind: str) -> None:
    """ValueError naming ``function(name)`` where ``items`` holds none (an empty list had
    failed in ``max()`` without naming the argument), TypeError where it is no sequence."""
    if isinstance(items, str | bytes) or not isinstance(items, Sequence):
        raise TypeError(f"{function}: {name} must be a sequence of {kind}, got {type(items).__name__}")
    if len(items) == 0:
        raise ValueError(f"{function}: {name} is empty; expected at least one {kind} (one per heliostat or facet)")


MAX_RESOLUTION = 4096
"""Most sample points along one facet edge of :func:`ideal_surface` (16.7 million per facet)."""


def stack_surfaces(surfaces: Sequence[SurfacePoints]) -> SurfacePoints:
    """Stack unbatched surfaces with different point counts into a batch ``(h, p_max)``,
    padding with zero-area points."""
    _check_some("stack_surfaces", "surfaces", surfaces, "SurfacePoints")
    n = max(s.n_points for s in surfaces)
    padded = [s.pad_to(n) for s in surfaces]
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *padded)


# --------------------------------------------------------------------------------------
# Facet layout (PAINT heliostat properties)
# --------------------------------------------------------------------------------------


_HALF_EDGE = f"a finite half-{{}} edge vector at least {MIN_FACET_HALF_SIZE_M:g} m long (zero: a facet of no area)"
_NOT_PARALLEL = f"an edge at an angle to canting_e whose sine is >= {MIN_CANTING_SINE:g} (parallel: a facet of no area)"


@typing.final
class FacetLayout(eqx.Module):
    """Facets of a heliostat in the surface frame (m); batched with leading axes.

    Attributes:
        translations: ``(*b, f, 3)`` facet centres.
        canting_e: ``(*b, f, 3)`` half-width edge vectors (direction includes canting).
        canting_n: ``(*b, f, 3)`` half-height edge vectors.
        mask: ``(*b, f)`` True for real facets (False = padding).

    Raises:
        ValueError: fields of disagreeing shapes or, for a real facet (values known,
            not under ``jit``), a non-finite translation or canting vector, one shorter
            than ``MIN_FACET_HALF_SIZE_M`` (1 mm) (a facet of zero width or
            height) or two (nearly) parallel ones (the properties reader's rules),
            naming the facet and the field.
    """

    translations: Float[Array, "*b f 3"]
    canting_e: Float[Array, "*b f 3"]
    canting_n: Float[Array, "*b f 3"]
    mask: Bool[Array, "*b f"]

    def __check_init__(self):
        shapes = [jnp.shape(x) for x in (self.translations, self.canting_e, self.canting_n)]
        if len(set(shapes)) != 1 or len(shapes[0]) < 2 or shapes[0][-1] != 3 or jnp.shape(self.mask) != shapes[0][:-1]:
            raise ValueError(
                f"FacetLayout: translations {shapes[0]}, canting_e {shapes[1]}, canting_n {shapes[2]} and mask "
                f"{jnp.shape(self.mask)}; expected (..., f, 3) each and mask (..., f), one row per facet"
            )
        # values, where known (not under jit / vmap): a facet of zero width or height, or
        # of NaN or parallel edges, had a NaN normal and an area of 0 or NaN, so its rays
        # were lost (or NaN) without a word. The thresholds of the properties reader.
        t, e, n, mask = (known_values(x) for x in (self.translations, self.canting_e, self.canting_n, self.mask))
        if t is None or e is None or n is None or mask is None:
            return
        real = mask.astype(bool)
        length_e, length_n = np.linalg.norm(e, axis=-1), np.linalg.norm(n, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            sine = np.linalg.norm(np.cross(e, n), axis=-1) / (length_e * length_n)
        problems = (
            ("translations", t, ~np.isfinite(t).all(axis=-1), "a finite facet centre (m)"),
            ("canting_e", e, ~(length_e >= MIN_FACET_HALF_SIZE_M), _HALF_EDGE.format("width")),
            ("canting_n", n, ~(length_n >= MIN_FACET_HALF_SIZE_M), _HALF_EDGE.format("height")),
            ("canting_n", n, ~(sine >= MIN_CANTING_SINE), _NOT_PARALLEL),
        )
        for name, value, bad, expected in problems:
            bad = bad & real
            if bad.any():
                at = tuple(int(k) for k in np.argwhere(bad)[0])
                where = f"facet {at[-1]}" + (f" of heliostat {', '.join(map(str, at[:-1]))}" if len(at) > 1 else "")
                raise ValueError(
                    f"FacetLayout: {where}: {name} is {np.round(value[at], 6).tolist()}; expected {expected} "
                    f"({int(bad.sum())} facet(s) bad)"
                )

    @classmethod
    def from_arrays(cls, translations, canting_e, canting_n, mask=None) -> FacetLayout:
        t = jnp.asarray(translations)
        m = jnp.ones(t.shape[:-1], bool) if mask is None else jnp.asarray(mask, bool)
        return cls(
            translations=t, canting_e=jnp.asarray(canting_e, t.dtype), canting_n=jnp.asarray(canting_n, t.dtype), mask=m
        )

    @property
    def n_facets(self) -> int:
        return self.mask.shape[-1]

    def normals(self) -> Float[Array, "*b f 3"]:
        """Unit facet normals ``normalize(canting_e x canting_n)``."""
        c = jnp.cross(self.canting_e, self.canting_n)
        return c / jnp.linalg.norm(c, axis=-1, keepdims=True)

    def areas(self) -> Float[Array, "*b f"]:
        """Facet areas ``4 |canting_e x canting_n|`` in m^2 (0 for padding)."""
        return (
            4.0
            * jnp.linalg.norm(jnp.cross(self.canting_e, self.canting_n), axis=-1)
            * self.mask.astype(self.canting_e.dtype)
        )


def _float_vector(data, file, field, n=3):
    try:
        v = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise DataError(file, field, f"not a numeric vector: {data!r}") from e
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise DataError(file, field, f"expected {n} finite numbers, got {data!r}")
    return v


def read_facet_layout(path: str | os.PathLike) -> FacetLayout:
    """Facet layout of a PAINT heliostat-properties JSON (``facet_properties.facets``,
    read by :func:`heliojax.paint.read_facets`).

    Raises:
        DataError: missing or malformed facet fields.
    """
    facets = read_facets(path)
    return FacetLayout.from_arrays(
        np.asarray([f.translation_vector for f in facets], np.float64),
        np.asarray([f.canting_e for f in facets], np.float64),
        np.asarray([f.canting_n for f in facets], np.float64),
    )


def stack_layouts(layouts: Sequence[FacetLayout]) -> FacetLayout:
    """Batch facet layouts with different facet counts (padding masked out)."""
    _check_some("stack_layouts", "layouts", layouts, "FacetLayout")
    n = max(lay.n_facets for lay in layouts)

    def pad(lay: FacetLayout) -> FacetLayout:
        k = n - lay.n_facets
        if k == 0:
            return lay
        dt = lay.translations.dtype
        e = jnp.zeros((k, 3), dt).at[:, 0].set(1e-3)
        nn = jnp.zeros((k, 3), dt).at[:, 1].set(1e-3)
        return FacetLayout(
            translations=jnp.concatenate([lay.translations, jnp.zeros((k, 3), dt)]),
            canting_e=jnp.concatenate([lay.canting_e, e]),
            canting_n=jnp.concatenate([lay.canting_n, nn]),
            mask=jnp.concatenate([lay.mask, jnp.zeros((k,), bool)]),
        )

    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[pad(lay) for lay in layouts])


def ideal_surface(layout: FacetLayout, resolution: tuple[int, int] = (32, 32)) -> SurfacePoints:
    """Flat canted facets sampled on a cell-centred ``resolution = (n_e, n_n)`` grid per facet.

    Point ``(i, j)`` of facet ``f`` is ``t_f + a_i canting_e_f + b_j canting_n_f`` with
    ``a_i = -1 + (2 i + 1) / n_e``; every point carries ``area_f / (n_e n_n)``.

    Returns:
        :class:`SurfacePoints` with ``(*b, f * n_e * n_n)`` points.

    Raises:
        ValueError: ``resolution`` not two whole numbers in ``[1, MAX_RESOLUTION]`` (0
            or a negative count had given a mirror of no points, 2.5 was cut to 2).
    """
    if isinstance(resolution, str | bytes) or len(resolution) != 2:
        raise ValueError(f"ideal_surface: resolution must be (n_e, n_n), got {resolution!r}"[:200])
    for axis, value in zip(("n_e", "n_n"), resolution, strict=True):
        problem = count_problem(value, MAX_RESOLUTION)
        if problem is not None:
            raise ValueError(f"ideal_surface: resolution {axis} {problem}")
    ne, nn = resolution
    a = jnp.asarray(-1.0 + (2.0 * np.arange(ne) + 1.0) / ne, layout.translations.dtype)
    b = jnp.asarray(-1.0 + (2.0 * np.arange(nn) + 1.0) / nn, layout.translations.dtype)
    t = layout.translations[..., :, None, None, :]
    lead = (1,) * (layout.canting_e.ndim - 1)  # the batch and facet axes
    pts = (
        t
        + a.reshape(lead + (-1, 1, 1)) * layout.canting_e[..., :, None, None, :]
        + b.reshape(lead + (1, -1, 1)) * layout.canting_n[..., :, None, None, :]
    )
    normals = jnp.broadcast_to(layout.normals()[..., :, None, None, :], pts.shape)
    areas = jnp.broadcast_to((layout.areas() / (ne * nn))[..., :, None, None], pts.shape[:-1])
    lead = pts.shape[:-4]
    return SurfacePoints(
        points=pts.reshape(lead + (-1, 3)),
        normals=normals.reshape(lead + (-1, 3)),
        areas=areas.reshape(lead + (-1,)),
    )


# --------------------------------------------------------------------------------------
# Deflectometry
# --------------------------------------------------------------------------------------


@typing.final
class Deflectometry(eqx.Module):
    """Measured facet surfaces, facet-local (canting built in), padded with a mask.

    Attributes:
        points: ``(*b, f, p, 3)`` m.
        normals: ``(*b, f, p, 3)`` unit.
        mask: ``(*b, f, p)`` True for measured points.
    """

    points: Float[Array, "*b f p 3"]
    normals: Float[Array, "*b f p 3"]
    mask: Bool[Array, "*b f p"]

    @classmethod
    def from_facets(cls, facets: Sequence[tuple[ArrayLike, ArrayLike]], n_points: int | None = None) -> Deflectometry:
        """Pad per-facet ``(points [n_i, 3], normals [n_i, 3])`` to a common count."""
        _check_some("Deflectometry.from_facets", "facets", facets, "(points, normals) pair")
        n = max(len(np.asarray(p)) for p, _ in facets)
        n = n if n_points is None else max(n, n_points)
        pts = np.zeros((len(facets), n, 3), np.float32)
        nrm = np.zeros((len(facets), n, 3), np.float32)
        nrm[..., 2] = 1.0
        mask = np.zeros((len(facets), n), bool)
        for i, (p, q) in enumerate(facets):
            k = len(p)  # pyright: ignore[reportArgumentType]
            pts[i, :k] = p
            nrm[i, :k] = q
            mask[i, :k] = True
        return cls(points=jnp.asarray(pts), normals=jnp.asarray(nrm), mask=jnp.asarray(mask))

    @property
    def n_facets(self) -> int:
        return self.mask.shape[-2]

    def counts(self) -> Array:
        """Measured points per facet."""
        return jnp.sum(self.mask, axis=-1)


def read_deflectometry(path: str | os.PathLike) -> Deflectometry:
    """A PAINT deflectometry HDF5 file (read by :mod:`heliojax.paint`) as
    :class:`Deflectometry` (facets and points padded, masked).

    Raises:
        DataError: unreadable file, no facet groups, bad shapes or non-finite values.
    """
    return Deflectometry.from_facets(read_deflectometry_facets(path))


def stack_deflectometry(items: Sequence[Deflectometry]) -> Deflectometry:
    """Batch deflectometry of several heliostats (facets and points padded)."""
    _check_some("stack_deflectometry", "items", items, "Deflectometry")
    nf = max(d.n_facets for d in items)
    npnt = max(d.mask.shape[-1] for d in items)

    def pad(d: Deflectometry) -> Deflectometry:
        f, p = d.mask.shape
        pts = jnp.zeros((nf, npnt, 3), d.points.dtype).at[:f, :p].set(d.points)
        nrm = jnp.zeros((nf, npnt, 3), d.normals.dtype).at[..., 2].set(1.0).at[:f, :p].set(d.normals)
        mask = jnp.zeros((nf, npnt), bool).at[:f, :p].set(d.mask)
        return Deflectometry(points=pts, normals=nrm, mask=mask)

    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *[pad(d) for d in items])


def deflectometry_surface(defl: Deflectometry, layout: FacetLayout) -> SurfacePoints:
    """Trace the measured points directly: facet ``f``'s points are shifted by its
    translation and each carries ``area_f / count_f`` (facet area from the layout)."""
    counts = jnp.maximum(defl.counts(), 1)
    areas_f = layout.areas()
    per_point = areas_f / counts.astype(areas_f.dtype)
    pts = defl.points + layout.translations[..., :, None, :].astype(defl.points.dtype)
    areas = jnp.where(defl.mask, per_point[..., :, None], 0.0)
    lead = pts.shape[:-3]
    return SurfacePoints(
        points=pts.reshape(lead + (-1, 3)),
        normals=defl.normals.reshape(lead + (-1, 3)),
        areas=areas.reshape(lead + (-1,)).astype(pts.dtype),
    )


__all__ = [
    "Deflectometry",
    "FacetLayout",
    "SurfacePoints",
    "deflectometry_surface",
    "ideal_surface",
    "read_deflectometry",
    "read_facet_layout",
    "stack_deflectometry",
    "stack_layouts",
    "stack_surfaces",
    "write_deflectometry",
]
