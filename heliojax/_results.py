"""``results.h5``: what a calibration wrote, and :func:`load_results` to use it again.

Schema (``H`` heliostats, ``M`` padded records; NaN / -1 where no record):

* attrs: ``model`` (the model's label, e.g. ``"actuator"``,
  ``"stone8+backlash"``; ``"stone8+nn"``: a neural correction, whose network the file
  does not hold, so :func:`load_results` refuses it), ``split``, ``heliojax_version``,
  ``written_unix_time`` (s; a heliostat with a record time after it is flagged, a
  write time after the reader's clock warned of), ``param_names`` and
  ``param_units`` (JSON lists, vector order of :class:`heliojax.ParameterView`),
  ``free_params`` (JSON list), ``robust`` (bool), ``origin_lla`` (WGS84 lat deg,
  lon deg, alt m of the ENU origin), ``drift_mrad2_per_day`` (the fleet's
  pointing drift per tangent component, :func:`heliojax.temporal_drift`; 0 when not
  estimated), ``sky_gap_mrad2_per_deg`` (the predicted variance's growth per degree
  of sky gap, :func:`heliojax.temporal_drift`; 0 when absent), ``creep_mrad2_per_day2``
  (its growth per squared day from the fitted records' mean time,
  :func:`heliojax.days_from_fitted_mean`; 0 when absent), the predicted
  pointing-error law (:class:`heliojax.PointingErrorLaw`):
  ``tail_dof`` (degrees of freedom of a Student t; inf: a Gaussian core, also in files
  written without it), ``outlier_fraction`` and ``outlier_scale`` (the broad
  component of a two-component mixture; 0 and 1: none, also when absent)
* ``heliostat_ids`` ``(H,)`` str; ``target_names`` ``(T,)`` str
* ``params`` ``(H, P)`` float64, physical units; ``param_std`` ``(H, P)``
  Gauss-Newton standard errors; ``covariance`` ``(H, F, F)`` of the free parameters
* ``status`` ``(H,)`` int32 (:class:`heliojax.FitStatus`), ``status_labels`` ``(H,)`` str
  (the labels of ``summary.json``: ``no_training_records`` for ``FitStatus.NO_RECORDS``)
* ``noise_mrad`` ``(H,)`` noise per residual component (robust estimate)
* ``worse_than_nominal`` ``(H,)`` bool: the fit's leave-one-out RMS error on its
  training records is not below the uncalibrated model's (not used for aiming)
* ``start_geometry`` ``(H,)`` str: ``"nominal"`` or ``"fleet_typical"``
* ``geometry/...`` every field of the :class:`heliojax.HeliostatGeometry` the fit
  used (``geometry/position`` ``(H, 3)`` ENU m, ``geometry/actuators/increment``
  ``(H, 2)`` counts/m, ...): with ``params`` it reproduces the fitted models exactly
* per record ``(H, M)``: ``record_id`` int64 (-1 = padding), ``unix_time`` s,
  ``sun_azimuth_deg`` / ``sun_elevation_deg`` (PAINT convention: 0 = south,
  positive east), ``target_index`` int (into ``target_names``, -1 padding),
  ``split`` int8 (0 unused/padding, 1 train, 2 validation, 3 test), ``weight``
  (robust weight of a training record, 0 otherwise), ``outlier`` bool,
  ``superseded`` bool (a training record before the heliostat's change point,
  left out of the refit), ``off_target`` bool (its focal spot lies off its target,
  :func:`heliojax.spots_off_target`; :func:`load_results` flags a heliostat with most
  of its training records so),
  ``residual_mrad`` ``(H, M, 2)`` and ``residual_uncalibrated_mrad``,
  ``beam_error_mrad`` and ``beam_error_uncalibrated_mrad``, ``loo_mrad``
  (leave-one-out beam error of the records the fit used, NaN otherwise)
* with ``--test-data``: group ``test_data`` with ``record_id``, ``unix_time``,
  ``beam_error_mrad``, ``beam_error_uncalibrated_mrad`` ``(H, M')`` re-indexed to
  the fitted heliostats' rows
* group ``record_inputs``: the records' inputs, ``counts`` ``(H, M, 2)``,
  ``focal_spot`` ``(H, M, 3)`` ENU m, ``sun`` ``(H, M, 3)`` unit ENU vectors,
  ``temperature`` deg C, ``wind_speed`` m/s, ``wind_direction`` rad, ``approach``
  ``(H, M, 2)``: with ``params``, ``geometry`` and ``unix_time`` /
  ``target_index`` they reproduce ``residual_mrad``, which :func:`load_results`
  recomputes (one compiled program) and flags a heliostat whose stored residuals its
  parameters miss by more than :data:`RESIDUAL_TOLERANCE_MRAD` (a file with
  ``written_unix_time`` but without the group is refused; older files without either
  are read with a warning that they cannot be checked)
* ``row_checksum`` ``(H,)`` uint64, written last: per heliostat a 64-bit checksum of
  its rows of every other dataset with the file's attributes and ``target_names``.
  :func:`load_results` recomputes it and flags a heliostat whose rows changed since
  (an edit within every plausibility bound, e.g. of an actuator length, is found
  too); files without it (older versions) are not checked. It detects changes, it
  does not authenticate: whoever edits on purpose can recompute it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
import typing
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from ._aim import instant_seconds
from ._errors import DataError, HeliojaxError
from ._geometry import direction_to_azimuth_elevation, sun_direction
from ._heliostat import HeliostatGeometry, LinearActuators, RecordContext
from ._io import (
    H5_OUTSIDE_DATA_REFUSED,
    atomic_h5,
    check_path_argument,
    h5_first_outside_data,
    heliostat_id_problem,
    shown_value,
)
from ._kinematics import AbstractKinematicModel, nominal_model
from ._limits import LATEST_UNIX_S, target_name_problem
from ._parameters import ParameterView, broadcast_model, covariance_problem
from ._predictive import DRIFT_RATE_KEYS, MIN_TAIL_DOF, PointingErrorLaw
from ._splits import days_from_fitted_mean, days_since_fit, utc_iso
from ._version import __version__, release_tuple
from .effects import with_effects
from .fitting import FitStatus, residuals_mrad
from .paint._common import (
    MAX_HELIOSTAT_DISTANCE_M,
    MAX_HELIOSTAT_HEIGHT_M,
    MAX_HELIOSTAT_SIZE_M,
    actuator_bounds_kept,
    actuator_problem,
)
from .paint._flags import actuator_law_kept, actuator_law_problem, fleet_outliers

if typing.TYPE_CHECKING:
    import h5py

log = logging.getLogger(__name__)

SPLIT_CODES = {"unused": 0, "train": 1, "validation": 2, "test": 3}


def _geometry_items(geometry: eqx.Module, prefix: str = "geometry") -> dict[str, np.ndarray]:
    out = {}
    for f in dataclasses.fields(geometry):
        v = getattr(geometry, f.name)
        if isinstance(v, eqx.Module):
            out.update(_geometry_items(v, f"{prefix}/{f.name}"))  # type: ignore[arg-type]
        else:
            out[f"{prefix}/{f.name}"] = np.asarray(v)
    return out


def _read_geometry(
    group: h5py.Group, source: str, ids: tuple[str, ...], check_actuators: bool = True
) -> HeliostatGeometry:
    """The geometry of ``group``; its actuators are checked (:func:`_check_actuators`,
    unless ``check_actuators`` is False: a second read of the same group) before they
    are built, so that a bad one is named by its field and heliostat."""
    import h5py  # only for results files: ~35 ms of import a calibration without --out never needs

    def arr(name):
        if name not in group or not isinstance(group[name], h5py.Dataset):
            raise DataError(source, f"geometry/{name}", "missing dataset")
        value = np.asarray(group[name][()])  # pyright: ignore[reportIndexIssue]
        if value.dtype.kind not in "biuf":
            raise DataError(source, f"geometry/{name}", f"not numeric (dtype {value.dtype})")
        want = (n, 3 if name == "position" or name.endswith("translation") or "translation_" in name else 2)
        if value.shape != want:
            raise DataError(source, f"geometry/{name}", f"shape {value.shape}, expected {want}")
        if name == "ideal_axes" and not np.isin(value, (0, 1)).all():
            raise DataError(source, f"geometry/{name}", "not a flag (0 or 1, false or true)")
        return jnp.asarray(value)

    n = len(ids)
    raw = {f.name: arr(f"actuators/{f.name}") for f in dataclasses.fields(LinearActuators)}
    if check_actuators:
        _check_actuators({k: np.asarray(v, float) for k, v in raw.items()}, ids, source)
    act = LinearActuators(**raw)
    kw = {f.name: arr(f.name) for f in dataclasses.fields(HeliostatGeometry) if f.name != "actuators"}
    return HeliostatGeometry(actuators=act, **kw)


_GEOMETRY_ACTUATOR_NAMES = {
    "min_increment": "min_counts",
    "max_increment": "max_counts",
    "clockwise_axis_movement": "sign",
}
"""The geometry's names of the actuator keys of a properties file whose names differ."""


def _check_actuators(act: dict[str, np.ndarray], ids: tuple[str, ...], source: str) -> None:
    """DataError unless every actuator (``act``: the :class:`LinearActuators` fields,
    ``(H, 2)`` each) is finite and keeps the properties reader's bounds
    (:func:`~heliojax.paint._common.actuator_problem`,
    :func:`~heliojax.paint._flags.actuator_law_problem`; ``sign`` is +1 or -1 for
    ``clockwise_axis_movement`` 0 or 1), naming the first bad field and heliostat."""
    for name, value in act.items():
        bad = ~np.isfinite(value)
        if bad.any():
            h, i = np.argwhere(bad)[0]
            raise DataError(source, f"geometry/actuators/{name}", f"heliostat {ids[h]!r} axis {i + 1}: not finite")
    sign = act["sign"]
    clockwise = np.where(sign == 1.0, 0, np.where(sign == -1.0, 1, -1))
    fleet = {
        "increment": act["increment"],
        "offset": act["offset"],
        "pivot_radius": act["pivot_radius"],
        "initial_stroke_length": act["initial_stroke_length"],
        "initial_angle": act["initial_angle"],
        "min_increment": act["min_counts"],
        "max_increment": act["max_counts"],
        "clockwise_axis_movement": clockwise,
    }
    broken = ~(actuator_bounds_kept(fleet) & actuator_law_kept(fleet))  # (H, 2), one vectorised screen
    for h, i in np.argwhere(broken)[:1]:  # the first broken actuator, named by the readers' own checks
        a = {key: value[h, i].item() for key, value in fleet.items()}
        problem = actuator_problem(a)
        if problem is None and (law := actuator_law_problem(a)) is not None:
            problem = ("", law)
        if problem is not None:
            key, reason = problem
            if key == "clockwise_axis_movement":
                reason = f"must be +1 or -1, got {float(sign[h, i])!r}"
            field = "/".join(("geometry/actuators", _GEOMETRY_ACTUATOR_NAMES.get(key, key))).rstrip("/")
            raise DataError(source, field, f"heliostat {ids[h]!r} axis {i + 1}: {reason}")


def _check_geometry(geometry: HeliostatGeometry, ids: tuple[str, ...], source: str) -> None:
    """DataError unless every heliostat's (finite) geometry keeps the properties reader's
    bounds: every mount translation within
    :data:`~heliojax.paint._common.MAX_HELIOSTAT_SIZE_M`, a nonzero Stone slope (the
    actuators were checked as they were read, :func:`_read_geometry`)."""
    act = {f.name: np.asarray(getattr(geometry.actuators, f.name), float) for f in dataclasses.fields(LinearActuators)}
    for name in ("joint_translation_1", "joint_translation_2", "concentrator_translation"):
        far = np.abs(np.asarray(getattr(geometry, name), float)) > MAX_HELIOSTAT_SIZE_M
        if far.any():
            h = int(np.argwhere(far)[0, 0])
            raise DataError(
                source,
                f"geometry/{name}",
                f"heliostat {ids[h]!r}: more than {MAX_HELIOSTAT_SIZE_M:g} m, not an offset within a heliostat",
            )
    slope = np.asarray(geometry.linear_slope, float)
    intercept = np.asarray(geometry.linear_intercept, float)
    # the joint's turn over the count range (an actuator's is below pi): a slope of 1e300 aimed
    # with 0 counts, one of 1e-300 (or an intercept of 1e300) with counts of 300 digits
    swing = np.abs(slope) * (act["max_counts"] - act["min_counts"])
    for field, bad, reason in (
        ("linear_slope", slope == 0, lambda h, i: "zero (the counts move no joint)"),
        (
            "linear_slope",
            ~((swing >= MIN_SWING_RAD) & (swing <= MAX_SWING_RAD)),
            lambda h, i: (
                f"turns the joint {swing[h, i]:.3g} rad over the count range, "
                f"outside [{MIN_SWING_RAD:g}, {MAX_SWING_RAD:.3g}]"
            ),
        ),
        (
            "linear_intercept",
            ~(np.abs(intercept) <= MAX_SWING_RAD),
            lambda h, i: f"{float(intercept[h, i])!r} rad, more than {MAX_SWING_RAD:.3g} (two turns)",
        ),
    ):
        if bad.any():
            h, i = np.argwhere(bad)[0]
            raise DataError(source, f"geometry/{field}", f"heliostat {ids[h]!r} axis {i + 1}: {reason(h, i)}")


MIN_SWING_RAD = 1e-3
MAX_SWING_RAD = 4 * math.pi
"""Bounds of a joint's turn over its count range (rad; an actuator's is below pi) and of
the Stone map's angle at count 0 (two turns)."""


def model_from_label(label: str, dtype: typing.Any = jnp.float64) -> AbstractKinematicModel:
    """The nominal model of a label written by :meth:`AbstractKinematicModel.label`
    (``"actuator"``, ``"stone8+backlash+thermal"``); neural corrections are not
    stored in ``results.h5``."""
    base, *effects = label.split("+")
    if "nn" in effects:
        raise DataError(
            None,
            "model",
            f"a model with a neural correction ({label!r}) cannot be rebuilt from results.h5 (the network is "
            "not stored, and its residuals are not those of the kinematic parameters): aim, plan and trace need "
            f"the results of `heliojax calibrate --model {base}`",
        )
    try:
        model = nominal_model(base, dtype)
        return with_effects(model, effects) if effects else model
    except (ValueError, KeyError, TypeError) as e:
        raise DataError(None, "model", f"unknown model label {label!r}: {e}") from None


CHECKSUM_DATASET = "row_checksum"
"""Dataset of results.h5 with one 64-bit checksum per heliostat (see :func:`_row_checksums`)."""

RECORD_INPUTS = "record_inputs"
"""Group of results.h5 with the fitted records' inputs (counts, focal spots, sun, weather,
approach directions), from which :func:`load_results` recomputes ``residual_mrad``."""

_RECORD_INPUT_TRAILING = {
    "counts": (2,),
    "focal_spot": (3,),
    "sun": (3,),
    "temperature": (),
    "wind_speed": (),
    "wind_direction": (),
    "approach": (2,),
}
"""The datasets of :data:`RECORD_INPUTS` and their axes after ``(heliostats, records)``."""

RESIDUAL_TOLERANCE_MRAD = 1e-6
"""Largest difference (mrad) between a stored residual component and the one its
heliostat's parameters give on its stored record inputs: both are the same float64
program's output (observed differences ~1e-12 mrad); an edited parameter moves them by
far more."""

_CLOCK_SKEW_S = 86_400.0
"""Slack (s) for clocks of different machines when a record time or the file's write
time is compared with a later one."""

_FILE_LEVEL = frozenset({"target_names"})
"""Datasets that describe the file, not a heliostat's row, whatever their length."""

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
"""An odd 64-bit constant (2^64 / golden ratio): the checksum's multipliers are its odd multiples."""


@typing.no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _word_sums(rows: np.ndarray) -> np.ndarray:
    """``(n,)`` uint64 polynomial checksum of each row of ``rows`` ``(n, B)`` uint8:
    the row's little-endian 64-bit words times odd multipliers, summed modulo 2^64
    (a change of any one word changes the sum)."""
    n, width = rows.shape
    words = -(-width // 8)
    padded = np.zeros((n, words * 8), np.uint8)
    padded[:, :width] = rows
    w = padded.view("<u8")
    with np.errstate(over="ignore"):
        k = (np.arange(words, dtype=np.uint64) * np.uint64(2) + np.uint64(1)) * _GOLDEN  # odd, distinct
        return (w * k[None, :]).sum(axis=1, dtype=np.uint64) + np.uint64(width)


@typing.no_type_check  # run per record or cell: the tests' run-time type checks cost more than its body
def _as_rows(value: typing.Any, n: int) -> np.ndarray:
    """``value`` (a dataset's or attribute's content) as ``(n, B)`` bytes, one row per
    heliostat (``n`` = 1: the whole value)."""
    x = np.asarray(value)
    if x.dtype == object or x.dtype.kind in "SU":
        flat = [v.encode() if isinstance(v, str) else bytes(v) for v in x.reshape(-1)]
        x = np.array(flat if flat else [b""], dtype=bytes).reshape(x.shape if flat else (1,))
    x = np.ascontiguousarray(x)
    head = np.frombuffer(f"{x.dtype.str}{x.shape[1:] if n > 1 else x.shape}".encode(), np.uint8)
    body = x.reshape(n, -1).view(np.uint8).reshape(n, -1) if x.size else np.zeros((n, 0), np.uint8)
    return np.concatenate([np.broadcast_to(head, (n, head.size)), body], axis=1)


def _row_checksums(f: typing.Any, n: int) -> np.ndarray:
    """``(n,)`` uint64: one checksum per heliostat over its rows of every dataset
    whose first axis is the heliostats', together with the file's attributes and
    file-level datasets (so an edit of those changes every heliostat's). Vectorised
    over the heliostats; no loop over them."""
    import h5py

    common = np.uint64(0)
    rows = np.zeros(n, np.uint64)
    with np.errstate(over="ignore"):
        for k in sorted(f.attrs):
            common = (
                common * np.uint64(1_000_003) + _word_sums(_as_rows(k, 1))[0] + _word_sums(_as_rows(f.attrs[k], 1))[0]
            )
        names: list[str] = []
        f.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
        for name in sorted(names):
            if name == CHECKSUM_DATASET:
                continue
            value = f[name][()]
            tag = _word_sums(_as_rows(name, 1))[0]
            per_row = name not in _FILE_LEVEL and np.ndim(value) >= 1 and np.shape(value)[0] == n
            if per_row:
                rows = rows * np.uint64(1_000_003) + tag + _word_sums(_as_rows(value, n))
            else:
                common = common * np.uint64(1_000_003) + tag + _word_sums(_as_rows(value, 1))[0]
        return rows * _GOLDEN + common


def write_results_h5(path: str | Path, run: typing.Any) -> None:
    """Write ``results.h5`` atomically for a :class:`heliojax.CalibrationRun`
    (schema in the module docstring).

    Raises:
        TypeError, ValueError: ``path`` is no path or empty (:func:`heliojax._io.check_path_argument`)."""
    import h5py  # only for results files: ~35 ms of import a calibration without --out never needs

    check_path_argument(path)
    n = len(run.summary["heliostats"])
    view = run.result.view
    split = np.zeros(run.train_mask.shape, np.int8)
    split[run.train_mask] = SPLIT_CODES["train"]
    split[run.val_mask] = SPLIT_CODES["validation"]
    split[run.test_mask] = SPLIT_CODES["test"]
    az, el = direction_to_azimuth_elevation(run.fleet.context.sun)
    mask = np.asarray(run.fleet.mask)
    str_dt = h5py.string_dtype()
    with atomic_h5(path) as f:
        # a +nn run's residuals and errors are the network's: its label says so, so that
        # no reader takes the file's kinematic parameters for the model behind them
        f.attrs["model"] = str(run.summary.get("model") or run.model0.label())
        f.attrs["split"] = run.split_kind
        f.attrs["heliojax_version"] = __version__
        f.attrs["written_unix_time"] = time.time()
        f.attrs["param_names"] = json.dumps(list(view.names))
        f.attrs["param_units"] = json.dumps(list(view.units))
        f.attrs["free_params"] = json.dumps(list(view.free_names))
        f.attrs["robust"] = bool(run.summary.get("robust", False))
        f.attrs["origin_lla"] = np.asarray(run.fleet.origin_lla, float)
        for key in _RATE_ATTRS:
            f.attrs[key] = float(run.predictive.get(key, 0.0))
        law = PointingErrorLaw.from_dict(run.predictive.get("error_law"))
        f.attrs["tail_dof"] = law.tail_dof
        f.attrs["outlier_fraction"] = law.outlier_fraction
        f.attrs["outlier_scale"] = law.outlier_scale
        f.create_dataset("heliostat_ids", data=np.array(run.fleet.ids[:n], dtype=object), dtype=str_dt)
        f.create_dataset("target_names", data=np.array(run.fleet.target_names, dtype=object), dtype=str_dt)
        f.create_dataset("params", data=np.asarray(run.result.parameters())[:n])
        f.create_dataset("param_std", data=np.asarray(run.result.std)[:n])
        f.create_dataset("covariance", data=np.asarray(run.result.covariance)[:n])
        f.create_dataset("status", data=np.asarray(run.result.status)[:n].astype(np.int32))
        # the summary's labels: a real heliostat with no record selected has none to train on
        labels = [
            "no_training_records" if x == FitStatus.NO_RECORDS.label else x for x in run.result.status_labels()[:n]
        ]
        f.create_dataset("status_labels", data=np.array(labels, dtype=object), dtype=str_dt)
        f.create_dataset("noise_mrad", data=np.asarray(run.noise_mrad, float)[:n])
        worse = run.summary["fleet"].get("worse_than_nominal", [])
        f.create_dataset("worse_than_nominal", data=np.array([i in worse for i in run.fleet.ids[:n]], bool))
        f.create_dataset("loo_mrad", data=np.asarray(run.result.loo_mrad, float)[:n])
        f.create_dataset(
            "start_geometry",
            data=np.array(["fleet_typical" if r else "nominal" for r in run.start_replaced[:n]], dtype=object),
            dtype=str_dt,
        )
        for name, value in _geometry_items(jax.tree.map(lambda x: np.asarray(x)[:n], run.fleet.geometry)).items():
            f.create_dataset(name, data=value)
        f.create_dataset("record_id", data=np.asarray(run.fleet.record_id)[:n].astype(np.int64))
        f.create_dataset("unix_time", data=np.where(mask, np.asarray(run.fleet.context.unix_time), np.nan)[:n])
        f.create_dataset("sun_azimuth_deg", data=np.where(mask, np.degrees(np.asarray(az)), np.nan)[:n])
        f.create_dataset("sun_elevation_deg", data=np.where(mask, np.degrees(np.asarray(el)), np.nan)[:n])
        f.create_dataset("target_index", data=np.where(mask, np.asarray(run.fleet.target_index), -1)[:n])
        f.create_dataset("split", data=split[:n])
        f.create_dataset("weight", data=np.asarray(run.weights, float)[:n])
        f.create_dataset("outlier", data=np.asarray(run.outlier, bool)[:n])
        superseded = run.superseded if run.superseded is not None else np.zeros(np.shape(run.outlier), bool)
        f.create_dataset("superseded", data=np.asarray(superseded, bool)[:n])
        off_target = run.off_target if run.off_target is not None else np.zeros(np.shape(run.outlier), bool)
        f.create_dataset("off_target", data=np.asarray(off_target, bool)[:n])
        f.create_dataset("residual_mrad", data=run.residuals_mrad[:n])
        # the records themselves: with params and geometry they reproduce residual_mrad,
        # which load_results checks (a parameter edited within every bound is found)
        context = run.fleet.context
        inputs = {
            "counts": run.fleet.counts,
            "focal_spot": run.fleet.focal_spot,
            "sun": context.sun,
            "temperature": context.temperature,
            "wind_speed": context.wind_speed,
            "wind_direction": context.wind_direction,
            "approach": context.approach,
        }
        for name, value in inputs.items():
            f.create_dataset(f"{RECORD_INPUTS}/{name}", data=np.asarray(value, float)[:n])
        f.create_dataset("residual_uncalibrated_mrad", data=run.uncalibrated_residuals_mrad[:n])
        f.create_dataset("beam_error_mrad", data=run.errors_mrad[:n])
        f.create_dataset("beam_error_uncalibrated_mrad", data=run.uncalibrated_mrad[:n])
        if run.test_errors_mrad is not None:
            g = f.create_group("test_data")
            g.create_dataset("beam_error_mrad", data=np.asarray(run.test_errors_mrad)[:n])
            g.create_dataset("beam_error_uncalibrated_mrad", data=np.asarray(run.test_uncalibrated_mrad)[:n])
        # last: what heliojax wrote, row by row (load_results flags rows changed since)
        f.create_dataset(CHECKSUM_DATASET, data=_row_checksums(f, n))


@typing.final
@dataclasses.dataclass(frozen=True)
class CalibrationResults:
    """A calibration read back from ``results.h5`` (:func:`load_results`), ready for
    aiming and plotting.

    Attributes:
        ids: heliostat ids ``(H,)``.
        model: the fitted models, batched over ``H`` (rebuilt from the model label
            and ``params``).
        geometry: the :class:`heliojax.HeliostatGeometry` the fit used, batched.
        view: the :class:`heliojax.ParameterView` (names, units, free set).
        status: ``(H,)`` status labels.
        params, param_std: ``(H, P)`` physical units.
        covariance: ``(H, F, F)`` of the free parameters.
        noise_mrad: ``(H,)``.
        worse_than_nominal: ``(H,)`` fits whose leave-one-out error on their
            training records is not below the uncalibrated model's (summary's
            ``worse_than_nominal``): not used for aiming.
        records: per-record arrays ``(H, M, ...)`` by dataset name (``record_id``,
            ``unix_time``, ``split``, ``weight``, ``outlier``, ``residual_mrad``, ...).
        attrs: the file's attributes.
        source: the file.
        target_names: the names ``records["target_index"]`` points into.
        flags: heliostat id -> why its fit is suspect: a position far from the
            fleet's (the properties reader's outlier rule), or rows of the file
            changed after heliojax wrote them (``row_checksum``), or most of its
            training records with their focal spot off their target (``off_target``,
            :func:`heliojax.calibrate`'s ``spots_off_target``); such a heliostat
            is not :attr:`fitted` (aim flags its commands ``unreliable``).
    """

    ids: tuple[str, ...]
    model: AbstractKinematicModel
    geometry: HeliostatGeometry
    view: ParameterView
    status: tuple[str, ...]
    params: np.ndarray
    param_std: np.ndarray
    covariance: np.ndarray
    noise_mrad: np.ndarray
    worse_than_nominal: np.ndarray
    records: dict[str, np.ndarray]
    attrs: dict[str, typing.Any]
    source: str
    target_names: tuple[str, ...] = ()
    flags: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def drift_mrad2_per_day(self) -> float:
        """The fleet's pointing drift (mrad^2 per day per tangent component; 0 in files
        written without one), :func:`heliojax.temporal_drift`."""
        return float(self.attrs.get("drift_mrad2_per_day", 0.0))

    @property
    def sky_gap_mrad2_per_deg(self) -> float:
        """The predicted variance's growth (mrad^2 per component) per degree of sky gap
        (0 in files written without it), :func:`heliojax.temporal_drift`."""
        return float(self.attrs.get("sky_gap_mrad2_per_deg", 0.0))

    @property
    def creep_mrad2_per_day2(self) -> float:
        """The predicted variance's growth (mrad^2 per component) per squared day from
        the fitted records' mean time (0 in files written without it),
        :func:`heliojax.temporal_drift`."""
        return float(self.attrs.get("creep_mrad2_per_day2", 0.0))

    @property
    def error_law(self) -> PointingErrorLaw:
        """The predicted pointing-error law (:func:`heliojax.temporal_drift`; the
        Gaussian in files written without one)."""
        return _error_law(self.attrs)

    def drift_variance_mrad2(self, unix_time: Float[ArrayLike, " N"]) -> Float[np.ndarray, "H N"]:
        """``(H, N)`` drift variance (mrad^2 per component) at ``unix_time`` (s): the
        drift rate times the fitted state's age in days (:func:`heliojax.days_since_fit`),
        plus the creep rate times the squared days from the mean time of the fitted
        records that are not outliers (:func:`heliojax.days_from_fitted_mean`); NaN
        for a heliostat without a fitted record.

        Raises:
            ValueError: ``unix_time`` not seconds since 1970 between 1970 and 2200
                (milliseconds, nanoseconds, NaN), as :func:`heliojax.aim_results`.
        """
        when = np.atleast_1d(instant_seconds(unix_time))
        variance = np.zeros((len(self.ids), when.size))
        if self.drift_mrad2_per_day == 0.0 and self.creep_mrad2_per_day2 == 0.0:
            return variance
        if self.drift_mrad2_per_day != 0.0:
            age = days_since_fit(self.fitted_records(inliers=False), self.records["unix_time"], when)
            variance = variance + self.drift_mrad2_per_day * age
        if self.creep_mrad2_per_day2 != 0.0:
            days = days_from_fitted_mean(self.fitted_records(inliers=True), self.records["unix_time"], when)
            variance = variance + self.creep_mrad2_per_day2 * days**2
        return variance

    def fitted_records(self, *, inliers: bool) -> Bool[np.ndarray, "H M"]:
        """``(H, M)`` the training records the model was fitted to (not superseded by a
        change point), with ``inliers`` the outliers among them left out too.

        Raises:
            TypeError: ``inliers`` not a bool ("no" had been taken for True)."""
        if not isinstance(inliers, (bool, np.bool_)):
            raise TypeError(f"fitted_records: inliers must be True or False, got {inliers!r}"[:200])
        fitted = self.records["split"] == 1
        for name in ("superseded", "outlier") if inliers else ("superseded",):
            if name in self.records:
                fitted = fitted & ~self.records[name].astype(bool)
        return fitted

    def fitted_sun(self) -> tuple[Float[np.ndarray, "H M 3"], Bool[np.ndarray, "H M"]] | None:
        """``(sun, fitted_record)``: ``(H, M, 3)`` unit ENU vectors to the sun of every
        record (0 where unknown) and ``(H, M)`` the records the model was fitted to:
        training records, not outliers, not superseded by a change point, with a sun.
        None when the file holds no per-record suns or split."""
        if not {"sun_azimuth_deg", "sun_elevation_deg", "split"} <= self.records.keys():
            return None
        az = np.radians(np.asarray(self.records["sun_azimuth_deg"], float))
        el = np.radians(np.asarray(self.records["sun_elevation_deg"], float))
        known = np.isfinite(az) & np.isfinite(el)
        sun = np.asarray(sun_direction(np.where(known, az, 0.0), np.where(known, el, 0.0)))
        return np.where(known[..., None], sun, 0.0), self.fitted_records(inliers=True) & known

    @property
    def fitted(self) -> np.ndarray:
        """``(H,)`` heliostats with a usable fit: converged or at the step limit, not
        flagged ``worse_than_nominal``, and a geometry without a :attr:`flags` entry."""
        ok = (FitStatus.CONVERGED.label, FitStatus.MAX_STEPS.label)
        usable = np.array([s in ok and h not in self.flags for s, h in zip(self.status, self.ids)])
        return usable & ~self.worse_than_nominal

    def heliostat(self, heliostat_id: str) -> tuple[AbstractKinematicModel, HeliostatGeometry]:
        """The fitted model and geometry of one heliostat."""
        if heliostat_id not in self.ids:
            raise KeyError(f"heliostat {heliostat_id!r} is not in {self.source}")
        i = self.ids.index(heliostat_id)
        take = lambda x: x[i] if eqx.is_array(x) else x  # noqa: E731
        return jax.tree.map(take, self.model), jax.tree.map(take, self.geometry)


_LATEST_UNIX_TIME = LATEST_UNIX_S
"""2200-01-01T00:00Z in unix seconds: a later record time is a unit mistake (ms, us)."""
_RECORD_TRAILING = {"residual_mrad": (2,), "residual_uncalibrated_mrad": (2,)}
"""Axes of a per-record dataset after its ``(heliostats, records)`` ones (east and north
components of a residual); none for the others."""
_RECORD_FIELDS = (
    "record_id",
    "unix_time",
    "sun_azimuth_deg",
    "sun_elevation_deg",
    "target_index",
    "split",
    "weight",
    "outlier",
    "residual_mrad",
    "residual_uncalibrated_mrad",
    "beam_error_mrad",
    "beam_error_uncalibrated_mrad",
    "loo_mrad",
    "superseded",
    "off_target",
)


_MAX_RESIDUAL_MRAD = 1e6
"""Largest magnitude of a stored residual component (mrad): no pointing error is a
thousand radians; a larger one is a forged or corrupted value."""
_ANGLE_RANGES_DEG = {"sun_azimuth_deg": (-360.0, 360.0), "sun_elevation_deg": (-90.0, 90.0)}
"""Where a record's sun angles (degrees) must lie."""


def _check_record_ranges(records: dict[str, np.ndarray], source: str) -> None:
    """Residuals within :data:`_MAX_RESIDUAL_MRAD`, and the sun angles of the fit's
    records (``split`` not 0) finite and within :data:`_ANGLE_RANGES_DEG` (padding may
    hold NaN)."""
    for key in ("residual_mrad", "residual_uncalibrated_mrad"):
        if key in records:
            values = records[key]
            big = np.abs(values[np.isfinite(values)])
            if big.size and big.max() > _MAX_RESIDUAL_MRAD:
                raise DataError(source, key, f"{big.max():.6g} mrad: no pointing error exceeds {_MAX_RESIDUAL_MRAD:g}")
    fitted = records["split"] != 0 if "split" in records else None
    for key, (low, high) in _ANGLE_RANGES_DEG.items():
        if key not in records:
            continue
        values = records[key]
        if fitted is not None and not np.isfinite(values[fitted]).all():
            raise DataError(source, key, "not finite for a record of the fit's split")
        finite = values[np.isfinite(values)]
        if finite.size and not ((finite >= low) & (finite <= high)).all():
            bad = finite[(finite < low) | (finite > high)][0]
            raise DataError(source, key, f"{bad!r} deg is outside {low:g}..{high:g} deg")


_MAX_RECORD_ID = 2**31
"""Record ids are PAINT's, integers in ``[0, 2**31)`` (:func:`heliojax.records_among`
keys them so); -1 marks padding."""
_BOOLEAN_RECORD_FIELDS = ("outlier", "superseded", "off_target")
"""Per-record flags heliojax writes as booleans."""


def _check_record_codes(records: dict[str, np.ndarray], ids: tuple[str, ...], source: str) -> None:
    """The record ids, weights and flags as heliojax writes them (round 11b: a float, a
    repeated or a negative record id was read, and plan took a fitted record for a new
    candidate; a NaN or negative weight; an outlier flag of 2): DataError naming the
    field otherwise."""
    if "record_id" in records:
        rid = records["record_id"]
        if rid.dtype.kind not in "iu":
            raise DataError(source, "record_id", f"not integers (dtype {rid.dtype})")
        wrong = (rid < -1) | (rid >= _MAX_RECORD_ID)
        if wrong.any():
            raise DataError(
                source,
                "record_id",
                f"{int(rid[wrong][0])} is not a record id (integers in [0, 2**31); -1 marks padding)",
            )
        if "split" in records and ((rid == -1) & (records["split"] != 0)).any():
            raise DataError(source, "record_id", "-1 (padding) for a record of the fit's split")
        ordered = np.sort(rid, axis=-1)  # all heliostats at once; padding (-1) may repeat
        twice = (ordered[..., 1:] == ordered[..., :-1]) & (ordered[..., 1:] >= 0)
        if twice.any():
            h, j = (int(i[0]) for i in np.nonzero(twice))
            raise DataError(source, "record_id", f"record {int(ordered[h, j + 1])} of {ids[h]!r} is listed twice")
    if "weight" in records:
        weight = records["weight"]
        if not ((weight >= 0.0) & (weight <= 1.0)).all():  # NaN too: the writer's weights are in [0, 1]
            bad = weight[~((weight >= 0.0) & (weight <= 1.0))][0]
            raise DataError(source, "weight", f"{shown_value(float(bad))} is not a record weight in [0, 1]")
    for key in _BOOLEAN_RECORD_FIELDS:
        if key in records and records[key].dtype.kind != "b":
            raise DataError(source, key, f"not booleans (dtype {records[key].dtype})")


def _note_newer_version(written_by: typing.Any, source: str) -> None:
    """Warn when the file was written by a newer heliojax than this one: what that version
    added or changed is not known here (read as far as this version understands it)."""
    if not isinstance(written_by, (str, bytes)):
        return
    text = written_by.decode(errors="replace") if isinstance(written_by, bytes) else written_by
    if "unknown" in __version__:  # a source tree that was never installed: nothing to compare with
        return
    if release_tuple(text) > release_tuple(__version__):
        log.warning(
            f"{source}: written by heliojax {text}, newer than this heliojax {__version__}: read as this version "
            "understands it (fields or meanings the newer one added are not known here)"
        )


_TIMED_RATES = ("drift_mrad2_per_day", "creep_mrad2_per_day2")
"""The rates of the predictive law that grow with the time since the fit: with either,
the records of the fit's split need their times."""
_RATE_ATTRS = ("drift_mrad2_per_day", *DRIFT_RATE_KEYS.values())
"""The predictive law's rates, kept as attributes of ``results.h5`` under their keys in
``summary.json``'s ``predictive`` (:func:`heliojax.temporal_drift`)."""
_LAW_ATTRS = (
    ("drift_mrad2_per_day", 0.0, 1e6),  # a beam spread by a radian a day is no calibration
    ("sky_gap_mrad2_per_deg", 0.0, 1e6),  # nor by a radian per degree of sky
    ("creep_mrad2_per_day2", 0.0, 1e6),  # nor by a radian a day from the fitted state
    ("tail_dof", MIN_TAIL_DOF, math.inf),
    ("outlier_fraction", 0.0, 1.0),
    ("outlier_scale", 0.0, math.inf),
)
"""Numeric attributes of results.h5 and their ranges."""


def _written_time(attrs: dict, source: str) -> float | None:
    """The file's ``written_unix_time`` (None in files written before it was kept);
    DataError when it is no time of 1970-2200."""
    if "written_unix_time" not in attrs:
        return None
    try:
        written = float(np.asarray(attrs["written_unix_time"]).item())
    except (TypeError, ValueError):
        raise DataError(source, "written_unix_time", f"not a number: {attrs['written_unix_time']!r}"[:200]) from None
    if not 0.0 <= written <= _LATEST_UNIX_TIME:  # NaN too
        raise DataError(source, "written_unix_time", f"{written!r} s is not a time of 1970-2200")
    return written


def _records_after(written: float, records: dict[str, np.ndarray], ids: tuple[str, ...]) -> dict[str, str]:
    """Heliostat id -> why its fit is not used, for the heliostats with a record later
    than the file's write time ``written`` (a forged time, or a record whose date the
    loader flagged as in the future and the fit kept)."""
    t = records.get("unix_time")
    if t is None:
        return {}
    with np.errstate(invalid="ignore"):
        later = np.isfinite(t) & (t > written + _CLOCK_SKEW_S)
    return {
        ids[h]: (
            f"unix_time: heliostat {ids[h]!r}: a record at {utc_iso(float(t[h][later[h]].max()))} is later than the "
            f"file was written ({utc_iso(written)}): a wrong record date, or an edited file"
        )
        for h in np.flatnonzero(later.any(axis=1))
    }


def _unreproduced_residuals(
    label: str,
    view: ParameterView,
    params: np.ndarray,
    geometry: HeliostatGeometry,
    inputs: dict[str, np.ndarray],
    records: dict[str, np.ndarray],
    usable: np.ndarray,
) -> dict[int, float]:
    """Heliostat index -> largest difference (mrad) between its stored residuals and
    those its parameters (``params`` ``(H, P)`` of the model ``label`` in ``view``'s
    order) give on the stored record inputs, for the usable heliostats where it exceeds
    :data:`RESIDUAL_TOLERANCE_MRAD`. In float64 whatever the caller's
    ``jax_enable_x64`` (``geometry`` read so); one compiled program over every heliostat
    and record (the calibration's own)."""
    stored = records["residual_mrad"]
    claimed = np.isfinite(stored).all(axis=-1) & usable[:, None]
    if not claimed.any():
        return {}
    n_rows = stored.shape[0]
    with jax.enable_x64(True):
        model = jax.vmap(view.from_vector)(broadcast_model(model_from_label(label), n_rows), jnp.asarray(params))
        context = RecordContext(
            sun=jnp.asarray(inputs["sun"]),
            unix_time=jnp.asarray(records.get("unix_time", np.full(stored.shape[:2], np.nan)), float),
            temperature=jnp.asarray(inputs["temperature"]),
            wind_speed=jnp.asarray(inputs["wind_speed"]),
            wind_direction=jnp.asarray(inputs["wind_direction"]),
            approach=jnp.asarray(inputs["approach"]),
            target=jnp.asarray(records.get("target_index", np.full(stored.shape[:2], -1)), jnp.int32),
        )
        counts, focal = jnp.asarray(inputs["counts"]), jnp.asarray(inputs["focal_spot"])
        recomputed = np.asarray(residuals_mrad(model, geometry, counts, context, focal, jnp.asarray(claimed)))
    with np.errstate(invalid="ignore"):
        difference = np.where(claimed[..., None], np.abs(recomputed - stored), 0.0)
    worst = np.nan_to_num(difference, nan=np.inf).reshape(n_rows, -1).max(axis=1)
    return {int(h): float(worst[h]) for h in np.flatnonzero(worst > RESIDUAL_TOLERANCE_MRAD)}


def _error_law(attrs: dict) -> PointingErrorLaw:
    """The pointing-error law of results.h5's attributes ``attrs`` (the Gaussian without
    them). Raises ValueError naming the attribute the law refuses."""
    return PointingErrorLaw(
        tail_dof=float(attrs.get("tail_dof", math.inf)),
        outlier_fraction=float(attrs.get("outlier_fraction", 0.0)),
        outlier_scale=float(attrs.get("outlier_scale", 1.0)),
    )


MAX_ORIGIN_ALTITUDE_M = 1e5
"""Largest ``|altitude|`` (m) of ``origin_lla``, the PAINT readers' bound for a point
near the Earth's surface (an altitude of 1e7 m was read, and aim then called the tower
file one of another plant)."""

_MAX_NOISE_MRAD = 1e4
"""Largest noise (mrad) of a usable fit: no beam misses by more than pi radians."""

_MAX_SCALED_STEP = 1e6
"""Most solver scales (:attr:`heliojax.ParameterView.scales`) a usable fit may lie
from the nominal parameters."""

_STATUS_LABELS = frozenset(s.label for s in FitStatus) | {"no_training_records"}
"""The status labels results.h5 may hold."""


def _check_covariance(cov: np.ndarray, source: str) -> None:
    """DataError unless every ``(F, F)`` matrix of ``cov`` (those of usable fits) is a
    finite, symmetric, positive semi-definite covariance (to rounding):
    :func:`heliojax._parameters.covariance_problem`."""
    problem = covariance_problem(cov)
    if problem == "not finite":
        problem = "not finite for a heliostat whose fit converged"
    if problem is not None:
        raise DataError(source, "covariance", problem)


def _numeric(
    value: typing.Any, source: str, field: str, shape: tuple[int | None, ...], kinds: str = "biuf"
) -> np.ndarray:
    """``value`` as a numeric array (of a dtype kind in ``kinds``) of shape ``shape``
    (``None``: any length on that axis), else DataError."""
    a = np.asarray(value)
    if a.dtype.kind not in kinds:
        what = "floating-point" if kinds == "f" else "numeric"
        raise DataError(source, field, f"not {what} (dtype {a.dtype})")
    if a.ndim != len(shape) or any(want is not None and got != want for got, want in zip(a.shape, shape, strict=True)):
        expected = (
            "("
            + ", ".join("M" if want is None else str(want) for want in shape)
            + ("," if len(shape) == 1 else "")
            + ")"
        )
        raise DataError(source, field, f"shape {a.shape}, expected {expected}")
    return a.astype(float) if a.dtype.kind == "f" else a


def _strings(value: typing.Any, source: str, field: str, n: int | None = None) -> tuple[str, ...]:
    """A 1-D dataset of strings (of length ``n``), else DataError."""
    a = np.asarray(value)
    if a.ndim != 1 or (n is not None and len(a) != n) or a.dtype.kind not in "OSU":
        raise DataError(
            source, field, f"expected {n if n is not None else 'a list of'} strings, got {a.dtype} {a.shape}"
        )
    try:
        return tuple(x.decode() if isinstance(x, bytes) else str(x) for x in a)
    except UnicodeDecodeError as e:
        raise DataError(source, field, f"not UTF-8 text ({e})") from None


def load_results(path: str | Path) -> CalibrationResults:
    """Read ``results.h5`` into a :class:`CalibrationResults` (models, the geometry
    the fit used, statuses, covariance, per-record residuals and times).

    Raises:
        DataError: naming the file and field when something is missing or malformed,
            or naming the file when HDF5 cannot read its structure (a damaged file).
        TypeError, ValueError: ``path`` is no path (None, an int, a list: they had been
            called damaged files) or empty (:func:`heliojax._io.check_path_argument`).
    """
    check_path_argument(path)
    try:
        return _load_results(path)
    except HeliojaxError:
        raise
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as e:  # h5py's errors of a damaged file
        raise DataError(str(path), None, f"damaged: HDF5 cannot read it ({type(e).__name__}: {e})"[:300]) from None


def _load_results(path: str | Path) -> CalibrationResults:
    """:func:`load_results`, whose errors of HDF5 itself it names."""
    import h5py  # only for results files: ~35 ms of import a calibration without --out never needs

    source = str(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise DataError(source, None, f"not a readable results.h5 ({e})") from e
    with f:
        outside = h5_first_outside_data(f)  # round 14: an external link read another results.h5
        if outside is not None:
            raise DataError(source, outside[0], H5_OUTSIDE_DATA_REFUSED.format(why=outside[1]))

        def need(name: str) -> typing.Any:
            if name not in f or not isinstance(f[name], h5py.Dataset):
                raise DataError(source, name, "missing dataset")
            try:
                return f[name][()]  # pyright: ignore[reportIndexIssue]
            except (OSError, ValueError, TypeError) as e:  # damaged or unreadable data
                raise DataError(source, name, f"unreadable dataset ({e})") from None

        attrs: dict[str, typing.Any] = {}
        for k in f.attrs:
            try:
                v = f.attrs[k]
                attrs[k] = v.decode() if isinstance(v, bytes) else v
            except (OSError, UnicodeDecodeError, TypeError, ValueError) as e:
                raise DataError(source, k, f"unreadable attribute ({e})") from None
        if "model" not in attrs and "aim_point_enu" in f:
            raise DataError(
                source, None, "is the HDF5 file of `heliojax aim`, not a results.h5 of `heliojax calibrate`"
            )
        for key in ("model", "param_names", "param_units"):
            if key not in attrs:
                raise DataError(source, key, "missing attribute")
        for key, default in (("param_names", None), ("param_units", None), ("free_params", "[]")):
            try:
                value = json.loads(attrs.get(key, default))
            except (ValueError, TypeError, RecursionError) as e:
                raise DataError(source, key, f"not a JSON list ({e})") from None
            if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
                raise DataError(source, key, f"not a JSON list of strings: {value!r}"[:200])
            attrs[key] = value
        names = tuple(attrs["param_names"])
        if len(attrs["param_units"]) != len(names):  # one unit per parameter, in the same order
            raise DataError(
                source, "param_units", f"{len(attrs['param_units'])} units for the {len(names)} param_names"
            )
        # the writer's types (round 11b: a forged robust of "no" or a numeric split was read)
        if "robust" in attrs and not isinstance(attrs["robust"], (bool, np.bool_)):
            raise DataError(source, "robust", f"not a boolean: {shown_value(attrs['robust'])}")
        if "split" in attrs and not isinstance(attrs["split"], str):
            raise DataError(source, "split", f"not the name of a split (text): {shown_value(attrs['split'])}")
        ids = _strings(need("heliostat_ids"), source, "heliostat_ids")
        if not ids:
            raise DataError(source, "heliostat_ids", "no heliostat")
        if len(set(ids)) != len(ids):
            raise DataError(source, "heliostat_ids", "an id is listed twice")
        bad = [(h, p) for h in ids if (p := heliostat_id_problem(h))]
        if bad:
            raise DataError(source, "heliostat_ids", f"{bad[0][0]!r} is not a heliostat id ({bad[0][1]})")
        changed = np.zeros(len(ids), bool)
        if CHECKSUM_DATASET in f:  # files of older heliojax versions have none
            stored = _numeric(need(CHECKSUM_DATASET), source, CHECKSUM_DATASET, (len(ids),), "u")
            try:
                changed = stored != _row_checksums(f, len(ids))
            except (OSError, ValueError, TypeError) as e:  # an unreadable dataset: named by the checks below
                log.debug(f"{source}: row checksums not computed ({e})")
        else:
            log.warning(
                f"{source}: no {CHECKSUM_DATASET} (a file of a heliojax before 2026-11-27, or one whose checksums "
                "were removed): values edited after it was written cannot be found"
            )
        params = _numeric(need("params"), source, "params", (len(ids), len(names)), "f")
        group = f.get("geometry")
        geometry = _read_geometry(group, source, ids) if isinstance(group, h5py.Group) else None
        if geometry is None:
            raise DataError(source, "geometry", "missing group (written by an older heliojax?)")
        records = {
            k: _numeric(need(k), source, k, (len(ids), None, *_RECORD_TRAILING.get(k, ())))
            for k in _RECORD_FIELDS
            if k in f
        }
        shapes = {
            k: v.shape[:2] for k, v in records.items() if k not in ("beam_error_mrad", "beam_error_uncalibrated_mrad")
        }
        for k, shape in shapes.items():
            if shape != next(iter(shapes.values())):
                raise DataError(source, k, f"shape {records[k].shape} differs from the other per-record datasets")
        targets = _strings(need("target_names"), source, "target_names") if "target_names" in f else ()
        # the tower reader's rule (round 11: a forged '=HYPERLINK(...)' or a name listed
        # twice was read, and plan matched the tower's targets to these names)
        bad_target = next(((t, p) for t in targets if (p := target_name_problem(t))), None)
        if bad_target is not None:
            raise DataError(
                source, "target_names", f"{shown_value(bad_target[0])} is not a target name ({bad_target[1]})"
            )
        if len(set(targets)) != len(targets):
            twice = next(t for t in targets if targets.count(t) > 1)
            raise DataError(source, "target_names", f"{shown_value(twice)} is listed twice")
        if "target_index" in records and np.any(records["target_index"] >= max(len(targets), 1)):
            raise DataError(source, "target_index", f"points beyond the {len(targets)} target_names")
        if "target_index" in records and np.any(records["target_index"] < -1):
            raise DataError(source, "target_index", "negative (-1 marks padding)")
        if "split" in records and not np.isin(records["split"], list(SPLIT_CODES.values())).all():
            raise DataError(source, "split", f"a code not among {sorted(SPLIT_CODES.values())} ({SPLIT_CODES})")
        _check_record_codes(records, ids, source)
        if "split" in records and "unix_time" in records:
            # NaN: unknown (a download without record times, split by record id); the drift
            # since the fit needs every time of the split, and a fit without times has none
            split_times = records["unix_time"][records["split"] != 0]
            if np.isinf(split_times).any():
                raise DataError(source, "unix_time", "not finite for a record of the fit's split")
            if np.isnan(split_times).any() and any(float(f.attrs.get(k, 0.0)) != 0.0 for k in _TIMED_RATES):
                raise DataError(
                    source, "unix_time", "unknown (NaN) for a record of the fit's split, with a drift since the fit"
                )
        if "unix_time" in records:
            timed = records["unix_time"][np.isfinite(records["unix_time"])]
            if timed.size and not ((timed >= 0) & (timed <= _LATEST_UNIX_TIME)).all():
                raise DataError(
                    source,
                    "unix_time",
                    f"{timed[(timed < 0) | (timed > _LATEST_UNIX_TIME)][0]!r} s is not a time "
                    "of 1970-2200 (seconds since 1970, UTC)",
                )
        _check_record_ranges(records, source)
        _note_newer_version(f.attrs.get("heliojax_version"), source)
        written = _written_time(attrs, source)
        inputs: dict[str, np.ndarray] = {}
        geometry64: HeliostatGeometry | None = None
        if RECORD_INPUTS in f and not isinstance(f[RECORD_INPUTS], h5py.Group):
            raise DataError(source, RECORD_INPUTS, "not a group")
        if RECORD_INPUTS not in f and "residual_mrad" in records:
            if written is not None:  # written together since 2026-12-07
                raise DataError(source, RECORD_INPUTS, "missing group, although the file says when it was written")
            log.warning(
                f"{source}: no {RECORD_INPUTS} (a file of a heliojax before 2026-12-07, or one whose group was "
                "removed): whether the parameters reproduce the stored residuals cannot be checked"
            )
        elif "residual_mrad" in records and isinstance(group, h5py.Group):  # the group (geometry read above)
            m = records["residual_mrad"].shape[1]
            inputs = {
                k: _numeric(need(f"{RECORD_INPUTS}/{k}"), source, f"{RECORD_INPUTS}/{k}", (len(ids), m, *tail), "f")
                for k, tail in _RECORD_INPUT_TRAILING.items()
            }
            with jax.enable_x64(True):  # the check compares float64 residuals, whatever the caller's setting
                geometry64 = _read_geometry(group, source, ids, check_actuators=False)  # checked above
        status = _strings(need("status_labels"), source, "status_labels", len(ids))
        unknown_status = sorted(set(status) - _STATUS_LABELS)
        if unknown_status:
            raise DataError(source, "status_labels", f"unknown status {unknown_status[0]!r}")
        if "status" in f:  # the codes of the labels (FitStatus), never another count of them
            codes = _numeric(need("status"), source, "status", (len(ids),), "iu")
            labels = {s.value: "no_training_records" if s == FitStatus.NO_RECORDS else s.label for s in FitStatus}
            wrong = [j for j, c in enumerate(codes) if labels.get(int(c)) != status[j]]
            if wrong:
                j = wrong[0]
                raise DataError(
                    source, "status", f"code {int(codes[j])} of {ids[j]!r} is not its status {status[j]!r} (FitStatus)"
                )
        std = _numeric(need("param_std"), source, "param_std", (len(ids), len(names)), "f")
        unknown = sorted(set(attrs["free_params"]) - set(names))
        if unknown:
            raise DataError(source, "free_params", f"{unknown} are not among param_names")
        free = len(attrs["free_params"]) or len(names)
        cov = _numeric(need("covariance"), source, "covariance", (len(ids), free, free), "f")
        has_noise = "noise_mrad" in f
        noise = (
            _numeric(need("noise_mrad"), source, "noise_mrad", (len(ids),), "f")
            if "noise_mrad" in f
            else np.full(len(ids), np.nan)
        )
        worse = (
            _numeric(need("worse_than_nominal"), source, "worse_than_nominal", (len(ids),)).astype(bool)
            if "worse_than_nominal" in f
            else np.zeros(len(ids), bool)
        )
    for key, low, high in _LAW_ATTRS:
        if key in attrs:
            try:
                x = float(attrs[key])
            except (TypeError, ValueError):
                raise DataError(source, key, f"not a number: {attrs[key]!r}") from None
            if math.isnan(x) or not low <= x <= high:
                raise DataError(source, key, f"{x} is outside [{low}, {high}]")
            attrs[key] = x
    try:  # the law's own checks (tail_dof 0, outlier_scale below 1)
        _error_law(attrs)
    except ValueError as e:
        key = next((k for k, _, _ in _LAW_ATTRS if k in str(e)), None)
        raise DataError(source, key, str(e)) from None
    origin = attrs.get("origin_lla")
    try:
        origin = np.asarray(origin, float) if origin is not None else None
    except (TypeError, ValueError):
        origin = np.full(1, np.nan)
    if origin is None:
        raise DataError(source, "origin_lla", "missing attribute")
    if origin.shape != (3,) or not np.isfinite(origin).all() or abs(origin[0]) > 90 or abs(origin[1]) > 180:
        raise DataError(source, "origin_lla", f"not a WGS84 latitude, longitude, altitude: {origin!r}"[:200])
    if abs(origin[2]) > MAX_ORIGIN_ALTITUDE_M:  # the PAINT readers' bound; was taken for another plant's tower
        raise DataError(source, "origin_lla", f"altitude {float(origin[2])!r} m is not near the Earth's surface")
    attrs["origin_lla"] = origin
    geometry_leaves = jax.tree_util.tree_leaves_with_path(geometry)
    for path_, leaf in geometry_leaves:
        if not np.isfinite(np.asarray(leaf, float)).all():
            name = "/".join(str(getattr(k, "name", k)) for k in path_)
            raise DataError(source, f"geometry/{name}", "not finite")
    _check_geometry(geometry, ids, source)
    usable = np.array([s in (FitStatus.CONVERGED.label, FitStatus.MAX_STEPS.label) for s in status])
    if not np.isfinite(params[usable]).all():
        raise DataError(source, "params", "not finite for a heliostat whose fit converged")
    # A fit whose records fix too few parameters (all at one pose) can converge without a
    # finite covariance: that heliostat is flagged below, the others stay usable.
    # (the fit writes such a covariance NaN throughout; a NaN entry among finite ones, or
    # an inf, is damage and named below)
    no_covariance = usable & np.isnan(cov).reshape(len(ids), -1).all(axis=1) & np.isnan(std).all(axis=1)
    _check_covariance(cov[usable & ~no_covariance], source)
    if has_noise and not ((noise[usable] >= 0) & (noise[usable] <= _MAX_NOISE_MRAD)).all():
        raise DataError(
            source,
            "noise_mrad",
            f"not a noise in [0, {_MAX_NOISE_MRAD:g}] mrad for a heliostat whose fit converged",
        )
    if "split" in records:
        fitted_records = (records["split"] != 0) & usable[:, None]
        for key in ("residual_mrad", "residual_uncalibrated_mrad"):
            if key in records and not np.isfinite(records[key][fitted_records]).all():
                raise DataError(source, key, "not finite for a record of a heliostat whose fit converged")
    if any(float(attrs.get(k, 0.0)) != 0.0 for k in _TIMED_RATES):
        for key in ("split", "unix_time"):
            if key not in records:
                raise DataError(source, key, "missing dataset (needed for the drift since the fit)")
    if float(attrs.get("sky_gap_mrad2_per_deg", 0.0)) != 0.0:
        for key in ("split", "sun_azimuth_deg", "sun_elevation_deg"):
            if key not in records:
                raise DataError(source, key, "missing dataset (needed for the sky gap of the predicted uncertainty)")
    records.setdefault("superseded", np.zeros(next(iter(shapes.values()), (len(ids), 0)), bool))
    try:
        template = model_from_label(str(attrs["model"]))
    except DataError as e:
        raise DataError(source, "model", e.reason) from None
    view = ParameterView.of(template)
    if view.names != names:
        raise DataError(
            source, "param_names", f"parameters {names} do not match model {attrs['model']!r} ({view.names})"
        )
    if attrs["free_params"]:
        try:
            view = view.with_free(attrs["free_params"])
        except (ValueError, KeyError) as e:
            raise DataError(source, "free_params", str(e)) from None
    # a usable fit moved a million solver scales (about a thousand radians of beam) from
    # nominal is garbage, not a calibration; nor is an uncertainty of as many
    scales = np.asarray(view.scales)
    free = list(view.free_index) if attrs["free_params"] else list(range(len(names)))
    spreads = [
        ("params", "is implausibly far from nominal", np.abs(params[usable] - np.asarray(view.nominal)), scales),
        ("param_std", "has an implausible standard error", std[usable & ~no_covariance], scales),
    ]
    if len(free) == cov.shape[-1]:
        diagonal = np.sqrt(np.abs(np.diagonal(cov[usable & ~no_covariance], axis1=-2, axis2=-1)))
        spreads.append(("covariance", "has an implausible variance", diagonal, scales[free]))
    for field, what, spread, scale in spreads:
        far = ~((spread >= 0) & (spread <= _MAX_SCALED_STEP * scale))  # NaN of a usable fit too
        if far.any():
            name = view.names[(free if field == "covariance" else list(range(len(names))))[int(np.argwhere(far)[0, 1])]]
            raise DataError(source, field, f"{name} {what} for a heliostat whose fit converged")
    position = np.asarray(geometry.position, float)
    far_off = np.hypot(position[:, 0], position[:, 1]) > MAX_HELIOSTAT_DISTANCE_M
    far_off |= np.abs(position[:, 2]) > MAX_HELIOSTAT_HEIGHT_M
    if far_off.any():
        raise DataError(
            source,
            "geometry/position",
            f"heliostat {ids[int(np.argmax(far_off))]!r} lies more than {MAX_HELIOSTAT_DISTANCE_M / 1000:g} km "
            f"or {MAX_HELIOSTAT_HEIGHT_M:g} m from the plant's origin",
        )
    # the properties reader's rule: an altitude from another datum, in feet, or 0 puts a
    # heliostat tens of metres above or below its neighbours; aimed with, silently, before
    flags = {
        ids[h]: f"geometry/position: heliostat {ids[h]!r} height {reason}"
        for h, reason in fleet_outliers(position[:, 2], MAX_HELIOSTAT_HEIGHT_M, "m")
    }
    for h in np.flatnonzero(no_covariance):
        flags.setdefault(
            ids[h],
            f"covariance: heliostat {ids[h]!r}: not finite although the fit converged (its records determine "
            "too few parameters: all at one pose, or repeated?)",
        )
    if {"off_target", "split"} <= records.keys():
        training = np.asarray(records["split"]) == SPLIT_CODES["train"]
        off = np.asarray(records["off_target"]).astype(bool) & training
        for h in np.flatnonzero(2 * off.sum(axis=1) > training.sum(axis=1)):
            flags.setdefault(
                ids[h],
                f"off_target: heliostat {ids[h]!r}: {int(off[h].sum())} of its {int(training[h].sum())} training "
                "records have their focal spot off their target, so its fit follows wrong spots",
            )
    if written is not None:
        for h, reason in _records_after(written, records, ids).items():
            flags.setdefault(h, reason)
    for reason in flags.values():
        log.warning(f"{source}: {reason}; its fit is not used")
    if changed.all() and len(ids) > 1:
        log.warning(
            f"{source}: {CHECKSUM_DATASET}: every heliostat's rows, or the file's attributes, changed after "
            "heliojax wrote them; no fit of this file is used"
        )
    elif changed.any():
        log.warning(
            f"{source}: {CHECKSUM_DATASET}: the rows of {', '.join(ids[h] for h in np.flatnonzero(changed))} "
            "changed after heliojax wrote them; their fits are not used"
        )
    for h in np.flatnonzero(changed):
        flags.setdefault(
            ids[h],
            f"{CHECKSUM_DATASET}: its rows of the file (or the file's attributes) changed after heliojax wrote them",
        )
    batched = broadcast_model(template, len(ids))
    model = jax.vmap(view.from_vector)(batched, jnp.asarray(params))
    if inputs and geometry64 is not None:
        unreproduced = _unreproduced_residuals(str(attrs["model"]), view, params, geometry64, inputs, records, usable)
        for h, difference in unreproduced.items():
            reason = (
                f"params: heliostat {ids[h]!r}: its parameters do not reproduce its residuals in the file (by up to "
                f"{difference:.3g} mrad): the parameters or the records were edited, or come from another fit"
            )
            log.warning(f"{source}: {reason}; its fit is not used")
            flags.setdefault(ids[h], reason)
    if written is not None and written > time.time() + _CLOCK_SKEW_S:
        log.warning(
            f"{source}: written_unix_time: written {utc_iso(written)}, later than this machine's clock: a wrong clock, "
            "or an edited file"
        )
    return CalibrationResults(
        ids=ids,
        model=model,
        geometry=geometry,
        view=view,
        status=status,
        params=params,
        param_std=std,
        covariance=cov,
        noise_mrad=noise,
        worse_than_nominal=worse,
        records=records,
        attrs=attrs,
        source=source,
        target_names=targets,
        flags=flags,
    )


__all__ = ["SPLIT_CODES", "CalibrationResults", "load_results", "model_from_label", "write_results_h5"]
