"""Parameters are fields of the model pytree: units, solver scale and typical size
live in the field's metadata, the free set is a boolean pytree of the model's shape.

A kinematic model (:class:`heliojax.StoneModel`, :class:`heliojax.ActuatorModel`,
an effect, a wrapper of them) is an :class:`equinox.Module`. Each fitted number
is a field declared with :func:`parameter`::

    class Backlash(AbstractEffect):
        width: Float[Array, "*h 2"] = parameter(unit="rad", scale=1e-3, typical=3e-4, name="backlash")

and each data-derived constant (a reference temperature, say) with
:func:`reference`. Nothing else describes the parameters: their names, order,
units and the solver's scaled vector are *derived* from the pytree by
:class:`ParameterView` (the one flat view the Levenberg-Marquardt solver and the
reports need). Which parameters are fitted is a pytree of booleans with the
model's structure (:func:`default_free`; change it with :func:`equinox.tree_at`),
so the free set is a partition of the model, not a list of name strings.

Names: a scalar field is named after the field (or its ``name``); a field of
shape ``(k,)`` gives ``name_1 .. name_k`` (or ``name_<suffix>`` with
``suffixes``); one of shape ``(r, k)`` gives ``name_1_<suffix> .. name_r_<suffix>``
(row-major, as the solver's vector).
"""

from __future__ import annotations

import collections.abc
import dataclasses
import math
import typing
from collections.abc import Iterator, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._geometry import check_numeric
from ._limits import real_problem

_META = "heliojax"

PathStep = str | int
Path = tuple[PathStep, ...]
ModuleT = typing.TypeVar("ModuleT", bound=eqx.Module)


@dataclasses.dataclass(frozen=True)
class ParameterInfo:
    """What a parameter field declares (see :func:`parameter`)."""

    unit: str
    scale: float
    typical: float | None
    name: str | None
    shape: tuple[int, ...]
    suffixes: tuple[str, ...] | None
    nominal: float
    above: float | None = None


@dataclasses.dataclass(frozen=True)
class ReferenceInfo:
    """What a reference field declares (see :func:`reference`)."""

    unit: str
    name: str | None
    default: float


def parameter(
    *,
    unit: str,
    scale: float,
    typical: float | None = None,
    name: str | None = None,
    shape: tuple[int, ...] = (),
    suffixes: Sequence[str] | None = None,
    nominal: float = 0.0,
    above: float | None = None,
    **kwargs: typing.Any,
) -> typing.Any:
    """An :func:`equinox.field` that declares a fitted parameter.

    A Python number, list or NumPy array given for it becomes a JAX array
    (:func:`field_array`); a module's ``__check_init__`` names a value that is no array
    of finite real numbers of the declared shape (:func:`check_fields`).

    Args:
        unit: physical unit label (``"rad"``, ``"1"``, ``"m"``, ...).
        scale: physical units per unit of the solver's scaled vector (chosen so
            that one scaled unit moves the beam by roughly 1-10 mrad, making the
            solver's tolerances read in physical terms).
        typical: a realistic physical size, documented a priori (discovery judges
            identifiability at this size).
        name: report name (default: the field name).
        shape: the field's shape for one heliostat (``()``, ``(k,)`` or ``(r, k)``).
        suffixes: element name suffixes of the last axis (default ``1..k``); a
            ``(r, k)`` field's elements are ``name_<row>_<suffix>``, rows from 1.
        nominal: the value that means "no correction".
        above: a value a (concrete) parameter must exceed (None: any finite value),
            e.g. 0 for a gear ratio the model divides by.
    """
    info = ParameterInfo(
        unit=unit,
        scale=float(scale),
        typical=None if typical is None else float(typical),
        name=name,
        shape=tuple(shape),
        suffixes=None if suffixes is None else tuple(suffixes),
        nominal=float(nominal),
        above=None if above is None else float(above),
    )
    return eqx.field(metadata={_META: info}, converter=field_array, **kwargs)


def reference(*, unit: str, default: float, name: str | None = None, **kwargs: typing.Any) -> typing.Any:
    """An :func:`equinox.field` that declares a data-derived constant (never fitted),
    e.g. the reference temperature of a thermal effect. ``default`` is used when the
    data cannot set it."""
    info = ReferenceInfo(unit=unit, name=name, default=float(default))
    return eqx.field(metadata={_META: info}, converter=field_array, **kwargs)


def field_array(value: typing.Any) -> typing.Any:
    """The converter of :func:`parameter` and :func:`reference` fields: a Python number,
    or a list or NumPy array of real numbers, becomes a JAX array (integers JAX's default
    float), put on the device without an eager XLA operation. A model built of Python
    floats (``StoneModel(alpha=0.0, ...)``) had failed in :func:`heliojax.fit` as
    "'float' object has no attribute 'shape'". JAX arrays (and traced values) are kept,
    and so is anything else: :func:`check_fields` names it."""
    if isinstance(value, jax.Array) or isinstance(value, (bool, np.bool_)):
        return value
    if not isinstance(value, (int, float, np.number, list, tuple, np.ndarray)):
        return value
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):  # a ragged list: named by check_fields
        return value
    if array.dtype.kind == "f":
        return jax.device_put(array)
    if array.dtype.kind in "iu":
        return jax.device_put(array.astype(jax.dtypes.canonicalize_dtype(np.float64)))
    return value


def check_fields(module: eqx.Module) -> None:
    """Check the parameter and reference fields of ``module`` (its own, not those of the
    modules inside it), each where its value is concrete (traced values under ``jit`` or
    ``vmap`` pass): called by the ``__check_init__`` of the kinematic models and the
    effects.

    Raises:
        TypeError: a value that is no array of real numbers (a string had failed inside
            the model's first use, None inside the fit, ``True`` had been 1 rad).
        ValueError: a value that is not finite (NaN had made every prediction NaN
            without a word), not above its field's ``above`` (a gear ratio of 0 divided
            by zero), or a parameter whose shape is not ``(*h, *shape)`` of its declared
            shape, or parameters batched over different heliostat axes.
    """
    who = type(module).__name__
    batches: dict[str, tuple[int, ...]] = {}
    for f in dataclasses.fields(module):
        info = f.metadata.get(_META)
        if not isinstance(info, (ParameterInfo, ReferenceInfo)):
            continue
        value = getattr(module, f.name)
        if isinstance(value, (jax.core.Tracer, jax.ShapeDtypeStruct)):  # pyright: ignore[reportAttributeAccessIssue]
            continue
        unit = "" if info.unit == "1" else f" ({info.unit})"
        check_numeric(value, f"{who}.{f.name}", f"real numbers{unit}, as a JAX array", bools=False)
        x = np.asarray(value, float)
        if isinstance(info, ParameterInfo):
            k = len(info.shape)
            if x.ndim < k or x.shape[x.ndim - k :] != info.shape:
                batched = str((None, *info.shape)).replace("None", "H")
                raise ValueError(
                    f"{who}.{f.name} has shape {x.shape}; expected {info.shape} for one heliostat "
                    f"(or {batched} for H heliostats)"
                )
            batches[f.name] = x.shape[: x.ndim - k]
        bad = ~np.isfinite(x)
        if isinstance(info, ParameterInfo) and info.above is not None:
            bad |= ~(x > info.above)
        if bad.any():
            above = f" and > {info.above:g}" if isinstance(info, ParameterInfo) and info.above is not None else ""
            at = f" at index {tuple(int(i) for i in np.argwhere(bad)[0])}" if x.ndim else ""
            raise ValueError(f"{who}.{f.name} must be finite{above}{unit}, got {float(x[bad].flat[0])}{at}")
    if len(set(batches.values())) > 1:
        shown = ", ".join(f"{name} {shape}" for name, shape in batches.items())
        raise ValueError(
            f"{who}: its parameters are batched over different heliostat axes ({shown}); "
            "give every parameter the same leading shape (H,), or none"
        )


@dataclasses.dataclass(frozen=True)
class ParameterLeaf:
    """One parameter field found in a model pytree.

    Attributes:
        path: attribute names / tuple indices from the root model to the field.
        info: its :class:`ParameterInfo`.
        names: element names (``size`` of them).
        fixed_by_model: the owning module declares it not fitted by default.
    """

    path: Path
    info: ParameterInfo
    names: tuple[str, ...]
    fixed_by_model: bool

    @property
    def size(self) -> int:
        return math.prod(self.info.shape)


@dataclasses.dataclass(frozen=True)
class ReferenceLeaf:
    """One reference field found in a model pytree."""

    path: Path
    info: ReferenceInfo
    name: str


def _element_names(name: str, info: ParameterInfo) -> tuple[str, ...]:
    if info.shape == ():
        return (name,)
    if len(info.shape) == 2:  # rows numbered from 1, then the suffixes of the last axis
        rows, k = info.shape
        inner = _element_names("", dataclasses.replace(info, shape=(k,)))
        return tuple(f"{name}_{r + 1}{s}" for r in range(rows) for s in inner)
    (k,) = info.shape
    suffixes = info.suffixes or tuple(str(i + 1) for i in range(k))
    if len(suffixes) != k:
        raise ValueError(f"parameter {name!r}: {len(suffixes)} suffixes for shape {info.shape}")
    return tuple(f"{name}_{s}" for s in suffixes)


def _walk(node: typing.Any, path: Path) -> Iterator[ParameterLeaf | ReferenceLeaf]:
    if isinstance(node, eqx.Module):
        fixed = set(getattr(node, "fixed_parameter_fields", lambda: ())())
        for f in dataclasses.fields(node):
            meta = f.metadata.get(_META)
            if isinstance(meta, ParameterInfo):
                name = meta.name or f.name
                yield ParameterLeaf(path + (f.name,), meta, _element_names(name, meta), f.name in fixed)
            elif isinstance(meta, ReferenceInfo):
                yield ReferenceLeaf(path + (f.name,), meta, meta.name or f.name)
            elif not f.metadata.get("static", False):
                yield from _walk(getattr(node, f.name), path + (f.name,))
    elif isinstance(node, (tuple, list)):
        for i, v in enumerate(node):
            yield from _walk(v, path + (i,))


def _get(node: typing.Any, path: Path) -> typing.Any:
    for step in path:
        node = node[step] if isinstance(step, int) else getattr(node, step)
    return node


def parameter_leaves(model: eqx.Module) -> tuple[ParameterLeaf, ...]:
    """Every parameter field of ``model``, in pytree order."""
    return tuple(x for x in _walk(model, ()) if isinstance(x, ParameterLeaf))


def reference_leaves(model: eqx.Module) -> tuple[ReferenceLeaf, ...]:
    """Every reference field of ``model``, in pytree order."""
    return tuple(x for x in _walk(model, ()) if isinstance(x, ReferenceLeaf))


def _bool_tree(model: eqx.Module, value: bool) -> typing.Any:
    return jax.tree.map(lambda _: value, model)


def default_free(model: eqx.Module) -> typing.Any:
    """The default free set of ``model``: a pytree of booleans with the model's
    structure, True for every parameter its module does not declare fixed
    (references and other leaves False). Change it with
    ``eqx.tree_at(lambda m: m.stroke_offset, free, True)``."""
    leaves = [leaf for leaf in parameter_leaves(model) if not leaf.fixed_by_model]
    free = _bool_tree(model, False)
    if not leaves:
        return free
    return eqx.tree_at(lambda t: [_get(t, leaf.path) for leaf in leaves], free, [True] * len(leaves))


def no_free(model: eqx.Module) -> typing.Any:
    """A free set with nothing free (a model evaluated as it is)."""
    return _bool_tree(model, False)


def _is_free(free: typing.Any, leaf: ParameterLeaf, model: typing.Any = None) -> bool:
    try:
        value = _get(free, leaf.path)
    except (AttributeError, IndexError, KeyError, TypeError):  # a free set of another model, or a dict of names
        raise TypeError(
            f"free set: no entry for {'.'.join(map(str, leaf.path))} of the model ({type(model).__name__}), "
            f"got a {type(free).__name__}; expected booleans of the model's structure "
            "(heliojax.default_free(model), changed with eqx.tree_at)"
        ) from None
    flat = np.asarray(value)
    if flat.dtype != bool:
        raise TypeError(f"free set at {'.'.join(map(str, leaf.path))}: expected booleans, got {value!r}")
    return bool(flat.all()) if flat.size else False


@dataclasses.dataclass(frozen=True)
class ParameterView:
    """The flat view of a model's parameters that solvers and reports use.

    Derived from a model (its structure, not its values) and a free set; static and
    hashable, so it can parametrise compiled programs. Element order is pytree
    order (a model's fields in declaration order, wrappers' inner models first).

    Attributes:
        leaves: the parameter fields.
        free_leaves: per leaf, whether it is fitted.
    """

    leaves: tuple[ParameterLeaf, ...]
    free_leaves: tuple[bool, ...]

    @classmethod
    def of(cls, model: eqx.Module, free: typing.Any = None) -> ParameterView:
        """The view of ``model`` (batched or not) with free set ``free`` (default
        :func:`default_free`)."""
        leaves = parameter_leaves(model)
        if free is None:
            free_leaves = tuple(not leaf.fixed_by_model for leaf in leaves)
        else:
            free_leaves = tuple(_is_free(free, leaf, model) for leaf in leaves)
        return cls(leaves, free_leaves)

    # -- element-wise tables ------------------------------------------------------

    @property
    def names(self) -> tuple[str, ...]:
        """Element names of every parameter, in vector order."""
        return tuple(n for leaf in self.leaves for n in leaf.names)

    @property
    def units(self) -> tuple[str, ...]:
        return tuple(leaf.info.unit for leaf in self.leaves for _ in range(leaf.size))

    @property
    def scales(self) -> tuple[float, ...]:
        return tuple(leaf.info.scale for leaf in self.leaves for _ in range(leaf.size))

    @property
    def typical(self) -> tuple[float | None, ...]:
        return tuple(leaf.info.typical for leaf in self.leaves for _ in range(leaf.size))

    @property
    def nominal(self) -> tuple[float, ...]:
        return tuple(leaf.info.nominal for leaf in self.leaves for _ in range(leaf.size))

    @property
    def free(self) -> tuple[bool, ...]:
        """Per element, whether it is fitted."""
        return tuple(f for leaf, f in zip(self.leaves, self.free_leaves) for _ in range(leaf.size))

    @property
    def free_index(self) -> tuple[int, ...]:
        return tuple(i for i, f in enumerate(self.free) if f)

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(self.names[i] for i in self.free_index)

    @property
    def n_parameters(self) -> int:
        return len(self.names)

    @property
    def n_free(self) -> int:
        return len(self.free_index)

    def with_free(self, free_names: Sequence[str]) -> ParameterView:
        """The same view with the leaves holding ``free_names`` free (whole leaves)."""
        wanted = set(free_names)
        unknown = wanted - set(self.names)
        if unknown:
            raise ValueError(f"unknown parameters {sorted(unknown)}; known: {self.names}")
        return dataclasses.replace(self, free_leaves=tuple(bool(wanted & set(leaf.names)) for leaf in self.leaves))

    def leaf_of(self, name: str) -> ParameterLeaf:
        for leaf in self.leaves:
            if name in leaf.names:
                return leaf
        raise ValueError(f"unknown parameter {name!r}; known: {self.names}")

    # -- vector <-> model -----------------------------------------------------------

    def to_vector(self, model: eqx.Module) -> Float[Array, "*b P"]:
        """Physical values of every parameter, ``(P,)`` (or ``(..., P)`` for a model
        batched along leading axes)."""
        xs = [_get(model, leaf.path) for leaf in self.leaves]
        if on_host(*xs) and len({x.dtype for x in xs}) == 1:
            # concrete arrays of one dtype: the same values without an eager XLA op per
            # call (each costs a lowering and a compilation-cache lookup in a new process)
            host = [np.asarray(x) for x in xs]
            return jax.device_put(
                np.concatenate(
                    [
                        np.reshape(x, x.shape[: x.ndim - len(leaf.info.shape)] + (leaf.size,))
                        for leaf, x in zip(self.leaves, host)
                    ],
                    axis=-1,
                )
            )
        parts = []
        for leaf in self.leaves:
            x = jnp.asarray(_get(model, leaf.path))
            batch = x.shape[: x.ndim - len(leaf.info.shape)]
            parts.append(jnp.reshape(x, batch + (leaf.size,)))
        return jnp.concatenate(parts, axis=-1)

    def _from_vectors(self, models: ModuleT, vectors: Float[Array, "H P"]) -> ModuleT:
        """``jax.vmap(self.from_vector)(models, vectors)``; for concrete arrays computed
        on the host (the same values, no eager XLA ops)."""
        if not self.leaves or not on_host(vectors, *jax.tree.leaves(models)):
            return jax.vmap(self.from_vector)(models, vectors)
        v = np.asarray(vectors)
        values = []
        start = 0
        for leaf in self.leaves:
            values.append(jax.device_put(np.reshape(v[:, start : start + leaf.size], (v.shape[0], *leaf.info.shape))))
            start += leaf.size
        return eqx.tree_at(lambda m: [_get(m, leaf.path) for leaf in self.leaves], models, values)

    def from_vector(self, model: ModuleT, vector: Float[Array, " P"]) -> ModuleT:
        """``model`` with its parameters replaced by ``vector`` (one heliostat: use
        :func:`jax.vmap` for batches). References and everything else stay."""
        values = []
        start = 0
        for leaf in self.leaves:
            values.append(jnp.reshape(vector[start : start + leaf.size], leaf.info.shape))
            start += leaf.size
        if not self.leaves:
            return model
        return eqx.tree_at(lambda m: [_get(m, leaf.path) for leaf in self.leaves], model, values)

    def scale_vector(self, dtype: typing.Any = None) -> Float[Array, " P"]:
        return jnp.asarray(self.scales, dtype)

    def free_scales(self, dtype: typing.Any = None) -> Float[Array, " F"]:
        return jnp.asarray([self.scales[i] for i in self.free_index], dtype)

    def scaled_to_model(self, model0: ModuleT, y: Float[Array, " F"]) -> ModuleT:
        """The model at scaled free-parameter offsets ``y`` from ``model0`` (physical
        ``p = p0 + y * scale`` on the free elements; one heliostat)."""
        p0 = self.to_vector(model0)
        idx = jnp.asarray(self.free_index, dtype=jnp.int32)
        p = p0.at[idx].add(y * self.free_scales(p0.dtype))
        return self.from_vector(model0, p)


def set_references(model: ModuleT, values: collections.abc.Mapping[str, float]) -> ModuleT:
    """``model`` with the references named in ``values`` set (others unchanged).

    Raises:
        ValueError: a name in ``values`` is none of the model's references (a
            misspelled one had been ignored without a word), or a value is not a
            finite real number.
    """
    known = [leaf.name for leaf in reference_leaves(model)]
    unknown = [str(k) for k in values if k not in known]
    if unknown:
        raise ValueError(
            f"set_references: unknown reference(s) {', '.join(map(repr, unknown))}; "
            f"the model's references are: {', '.join(known) if known else 'none'}"
        )
    for name, value in values.items():
        if isinstance(value, jax.core.Tracer):  # pyright: ignore[reportAttributeAccessIssue]
            continue  # a value under a trace is not known here
        problem = real_problem(value)
        if problem is not None:
            raise ValueError(f"set_references: {name} {problem}")
    leaves = [leaf for leaf in reference_leaves(model) if leaf.name in values]
    if not leaves:
        return model

    def where(m: eqx.Module) -> list[typing.Any]:
        return [_get(m, leaf.path) for leaf in leaves]

    new = [
        jnp.full(jnp.shape(_get(model, leaf.path)), values[leaf.name], jnp.asarray(_get(model, leaf.path)).dtype)
        for leaf in leaves
    ]
    return eqx.tree_at(where, model, new)


def on_host(*xs: typing.Any) -> bool:
    """Whether every ``x`` is a concrete array (NumPy, or JAX outside a trace): array
    plumbing on them (reshape, slice, broadcast, select) can be done with NumPy and the
    result put on the device, the same values without an eager XLA op each (each costs
    a lowering and a compilation-cache lookup in a new process)."""
    return all(
        isinstance(x, np.ndarray)
        or (isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer) and not x.weak_type)  # pyright: ignore[reportAttributeAccessIssue]
        for x in xs
    )


def and_masks(mask: typing.Any, valid: typing.Any) -> typing.Any:
    """``jnp.asarray(mask) & valid``; for concrete boolean arrays computed on the host
    (:func:`on_host`)."""
    if on_host(mask, valid) and mask.dtype == bool and valid.dtype == bool:
        return jax.device_put(np.asarray(mask) & np.asarray(valid))
    return jnp.asarray(mask) & valid


def broadcast_model(model: ModuleT, n: int) -> ModuleT:
    """``n`` copies of an unbatched model stacked along a new leading axis."""
    arrays = [x for x in jax.tree.leaves(model) if eqx.is_array(x)]
    if on_host(*arrays):
        return jax.tree.map(
            lambda x: jax.device_put(np.broadcast_to(np.asarray(x), (n, *np.shape(x)))) if eqx.is_array(x) else x,
            model,
        )
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x)) if eqx.is_array(x) else x, model)


def is_batched(model: eqx.Module) -> bool:
    """Whether ``model``'s parameters carry a leading heliostat axis."""
    leaves = parameter_leaves(model)
    if not leaves:
        arrays = [x for x in jax.tree.leaves(model) if eqx.is_array(x)]
        raise ValueError("is_batched: the model has no parameter fields" if arrays else "empty model")
    leaf = leaves[0]
    return jnp.ndim(_get(model, leaf.path)) > len(leaf.info.shape)


COVARIANCE_RTOL = 1e-6
"""Relative rounding (of a matrix's largest entry) allowed in :func:`covariance_problem`'s
symmetry and positive semi-definiteness checks."""


def covariance_problem(cov: Float[np.ndarray, "H F F"]) -> str | None:
    """What is wrong with a stack of ``(F, F)`` covariance matrices (``(H, F, F)``):
    ``"not finite"``, ``"not symmetric (heliostat h)"`` or ``"not positive
    semi-definite (heliostat h)"`` (to :data:`COVARIANCE_RTOL` of each matrix's
    largest entry); None when each is a finite, symmetric, positive semi-definite
    covariance. One batched check, not a loop over heliostats."""
    cov = np.asarray(cov, float)
    if not np.isfinite(cov).all():
        return "not finite"
    if cov.size == 0:
        return None
    scale = np.max(np.abs(cov), axis=(-2, -1))
    asymmetric = np.max(np.abs(cov - np.swapaxes(cov, -1, -2)), axis=(-2, -1)) > COVARIANCE_RTOL * scale
    if asymmetric.any():
        return f"not symmetric (heliostat {int(np.argmax(asymmetric))})"
    indefinite = np.linalg.eigvalsh(cov).min(axis=-1) < -COVARIANCE_RTOL * scale
    if indefinite.any():
        return f"not positive semi-definite (heliostat {int(np.argmax(indefinite))})"
    return None
