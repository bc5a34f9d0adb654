"""Inputs of the acceptance analysis: measured-field CSV, fleet-calibration
``summary.json`` plus heliostat positions, and the TOML contract."""

from __future__ import annotations

import dataclasses
import glob
import logging
import math
import os
import tomllib
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from .._errors import ConfigError, DataError, few_names
from .._geometry import MAX_FIELD_EXTENT_M, wgs84_to_enu
from .._io import check_path_argument, input_file_problem, is_decimal, read_csv_rows
from ..paint import TOWER_FILE_SUFFIX, read_heliostat_properties, read_tower
from ..paint._common import MAX_HELIOSTAT_HEIGHT_M, _load_json
from ._field import PARAMETERS, FieldData, value_problem

log = logging.getLogger(__name__)

_BAD_STATUS = {"failed", "error", "skipped", "excluded"} | {
    "diverged",
    "non_finite_input",
    "too_few_records",
    "no_records",
    "no_training_records",
}  # the last five: heliojax's own fit statuses of no calibration (its test error measures no heliostat)
_GOOD_STATUS = {"", "ok", "converged", "max_steps"}
"""Statuses of a calibrated heliostat (none given: calibrated); any other is an error."""


def _float(path, field, text) -> float:
    try:
        x = float(text)
    except (TypeError, ValueError):
        raise DataError(path, field, f"not a number: {text!r}") from None
    if not math.isfinite(x):
        raise DataError(path, field, f"not finite: {text!r}")
    if not is_decimal(text):
        raise DataError(path, field, f"not a decimal number: {text!r}")
    return x


MIN_HELIOSTAT_SPACING_M = 1.0
"""Smallest horizontal distance (m) between two heliostats' positions (pivots), and
between a heliostat and the tower (the receiver aperture's centre): two mirrors whose
pivots are closer than a mirror's side collide when stowed flat, and the smallest
heliostats built have mirrors of about 1 m (the Jülich heliostat's is 3.22 m x 2.56 m,
the PAINT properties' ``width`` and ``height``). A field closer than this is not a field
that can be built: its positions are in another unit (km for m puts heliostats
millimetres apart)."""


def check_spacing(
    path: str | os.PathLike,
    ids: tuple[str, ...],
    positions: np.ndarray,
    where: list[str] | None = None,
    *,
    min_spacing_m: float = MIN_HELIOSTAT_SPACING_M,
) -> None:
    """DataError naming ``path``, two heliostats and their distance where two of
    ``positions`` (``(n, 3)`` ENU m; only east and north count) are closer than
    ``min_spacing_m`` (m): mirrors that would collide, or positions in km.

    ``where``: per heliostat, where it was read (e.g. ``"line 3"``), named in the
    error. One k-d tree query (no loop over pairs): fields of 10,000 heliostats."""
    from scipy import spatial

    xy = np.asarray(positions, dtype=float)[:, :2]
    n = len(xy)
    if n < 2:
        return
    dist, near = spatial.cKDTree(xy).query(xy, k=2)  # pyright: ignore[reportAttributeAccessIssue]
    dist, near = np.asarray(dist), np.asarray(near)
    own = near[:, 0] == np.arange(n)  # the nearest is the point itself, except among duplicates
    other = np.where(own, near[:, 1], near[:, 0])
    d = np.where(own, dist[:, 1], dist[:, 0])
    close = np.flatnonzero(~(d >= min_spacing_m))
    if not close.size:
        return
    a, b = sorted((int(close[0]), int(other[close[0]])))  # the first heliostat in file order, its neighbour
    name = (lambda k: f"{ids[k]!r} ({where[k]})") if where is not None else (lambda k: repr(ids[k]))
    field = f"{where[b]}: east_m/north_m" if where is not None else "east_m/north_m"
    if d[close[0]] == 0.0:
        raise DataError(path, field, f"heliostats {name(a)} and {name(b)}: two heliostats in one place")
    raise DataError(
        path,
        field,
        f"heliostats {name(a)} and {name(b)} are {d[close[0]]:.3g} m apart, closer than a heliostat's mirror "
        f"({min_spacing_m:g} m; {int(close.size)} heliostat(s) so close): positions in km instead of m?",
    )


def tower_clearance_problem(
    ids: tuple[str, ...],
    positions: np.ndarray,
    tower_en: tuple[float, float],
    *,
    min_distance_m: float = MIN_HELIOSTAT_SPACING_M,
) -> str | None:
    """What is wrong where one of ``positions`` (``(n, 3)`` ENU m) is horizontally nearer
    than ``min_distance_m`` (m) to the tower at ``tower_en`` (east, north m: the receiver
    aperture's centre): its mirror would be in the tower, or the positions are in km;
    None where none is."""
    xy = np.asarray(positions, dtype=float)[:, :2]
    d = np.hypot(xy[:, 0] - tower_en[0], xy[:, 1] - tower_en[1])
    near = np.flatnonzero(~(d >= min_distance_m))
    if not near.size:
        return None
    k = int(near[0])
    return (
        f"heliostat {ids[k]!r} is {d[k]:.3g} m from the tower (east {tower_en[0]:.2f} m, north "
        f"{tower_en[1]:.2f} m), nearer than {min_distance_m:g} m ({int(near.size)} heliostat(s)): "
        "positions in km instead of m?"
    )


def read_field_csv(path: str | os.PathLike) -> FieldData:
    """Read ``heliostat_id,east_m,north_m[,up_m]`` plus any of
    ``tracking_mrad,slope_mrad,reflectance,aperture_m2`` (empty cell = not measured).

    Every row is a heliostat of the field (the population ``N``).

    Raises:
        DataError: missing columns, non-numeric or non-finite cells, duplicate IDs,
            values outside the parameter's support, two heliostats closer than
            :data:`MIN_HELIOSTAT_SPACING_M` (:func:`check_spacing`).
    """
    header, rows = read_csv_rows(path, "a field CSV")
    if not rows:
        raise DataError(path, None, "no rows")
    for col in ("heliostat_id", "east_m", "north_m"):
        if col not in header:
            raise DataError(path, col, "missing column")
    unknown = [c for c in header if c not in ("heliostat_id", "east_m", "north_m", "up_m", *PARAMETERS)]
    if unknown:
        raise DataError(path, str(unknown[0]), f"unknown column; known parameters: {sorted(PARAMETERS)}")
    params = [c for c in header if c in PARAMETERS]
    ids, pos = [], []
    vals = {p: [] for p in params}
    for i, row in rows:
        hid = (row["heliostat_id"] or "").strip()
        if not hid:
            raise DataError(path, f"line {i}: heliostat_id", "empty")
        if not hid.isprintable():  # a NUL or a line break inside quotes: not an id to print in a report
            raise DataError(path, f"line {i}: heliostat_id", f"{hid!r} holds unprintable characters")
        ids.append(hid)
        up = row.get("up_m")
        pos.append(
            [
                _float(path, f"line {i}: east_m", row["east_m"]),
                _float(path, f"line {i}: north_m", row["north_m"]),
                0.0 if up in (None, "") else _float(path, f"line {i}: up_m", up),
            ]
        )
        for p in params:
            cell = (row[p] or "").strip()
            x = math.nan if cell == "" else _float(path, f"line {i}: {p}", cell)
            problem = value_problem(p, x)
            if problem is not None:
                raise DataError(path, f"line {i}: {p}", problem)
            vals[p].append(x)
    if len(set(ids)) != len(ids):
        dup = sorted({h for h in ids if ids.count(h) > 1})[0]
        raise DataError(path, "heliostat_id", f"duplicate ID {dup!r}")
    for i, (e, n, u) in enumerate(pos, start=2):
        if max(abs(e), abs(n), abs(u)) > MAX_FIELD_EXTENT_M:
            raise DataError(
                path, f"line {i}: east_m/north_m/up_m", f"more than {MAX_FIELD_EXTENT_M:g} m from the tower"
            )
        if abs(u) > MAX_HELIOSTAT_HEIGHT_M:  # the PAINT reader's bound on a heliostat's height
            raise DataError(
                path,
                f"line {i}: up_m",
                f"{u:g} m: more than {MAX_HELIOSTAT_HEIGHT_M:g} m above or below the plant's reference point, "
                "not on its ground (millimetres, or another height datum?)",
            )
    check_spacing(path, tuple(ids), np.asarray(pos, dtype=float), [f"line {i}" for i in range(2, len(ids) + 2)])
    return FieldData(
        ids=tuple(ids),
        positions=np.asarray(pos, dtype=float),
        values={p: np.asarray(v, dtype=float) for p, v in vals.items()},
    )


def read_summary(path: str | os.PathLike) -> dict[str, float]:
    """Tracking errors from a fleet-calibration ``summary.json``.

    The tracking error of a heliostat is its ``test_rms_mrad`` (radial RMS beam
    pointing error on the held-out records). Heliostats whose ``status`` is
    failed / error / skipped / excluded (or a fit status of no calibration: diverged,
    non_finite_input, too_few_records, no_records, no_training_records), or whose ``test_rms_mrad`` is null or
    not finite with ``n_test`` 0 (no test records), count as not measured. A fitted heliostat without the
    key, or with a null or non-finite value although ``n_test`` > 0, is an error.

    Returns:
        heliostat ID -> tracking error (mrad).

    Raises:
        DataError: unreadable file, missing ``heliostats`` table, non-numeric value.
    """
    doc = _load_json(path)  # a key given twice (the json module kept the last) is an error
    table = doc.get("heliostats") if isinstance(doc, dict) else None
    if not isinstance(table, dict):
        raise DataError(path, "heliostats", "missing or not an object")
    if not table:
        raise DataError(path, "heliostats", "empty: no heliostat to judge")
    out = {}
    not_measured: list[str] = []
    for hid, rec in table.items():
        if not isinstance(rec, dict):
            raise DataError(path, f"heliostats.{hid}", "not an object")
        status = str(rec.get("status", "")).lower()
        if status in _BAD_STATUS:
            not_measured.append(f"{hid} ({status})")
            continue
        if status not in _GOOD_STATUS:
            raise DataError(path, f"heliostats.{hid}.status", f"unknown status {rec.get('status')!r}"[:200])
        if "test_rms_mrad" not in rec:  # calibrate writes it for every heliostat (null without test records)
            raise DataError(path, f"heliostats.{hid}.test_rms_mrad", "missing")
        x = rec.get("test_rms_mrad")
        n_test = rec.get("n_test")
        measured = isinstance(n_test, int) and not isinstance(n_test, bool) and n_test > 0
        if (x is None or (isinstance(x, float) and not math.isfinite(x))) and measured:
            raise DataError(
                path,
                f"heliostats.{hid}.test_rms_mrad",
                f"no value, though status {rec.get('status')!r} and n_test {n_test} say it was measured",
            )
        if x is None:
            not_measured.append(f"{hid} (no held-out records)")
            continue
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise DataError(path, f"heliostats.{hid}.test_rms_mrad", f"not a number: {x!r}")
        if math.isfinite(x):
            if not 0 < x <= PARAMETERS["tracking_mrad"].maximum:
                raise DataError(
                    path,
                    f"heliostats.{hid}.test_rms_mrad",
                    f"must be in (0, {PARAMETERS['tracking_mrad'].maximum:g}] mrad, got {x}",
                )
            out[hid] = float(x)
        else:
            not_measured.append(f"{hid} (no held-out records)")
    if not_measured:
        log.warning(f"{path}: {len(not_measured)} heliostat(s) count as not measured: {few_names(not_measured, 10)}")
    return out


def read_positions_csv(path: str | os.PathLike) -> tuple[tuple[str, ...], np.ndarray]:
    """Read ``heliostat_id,east_m,north_m[,up_m]`` (the whole field, ENU m)."""
    fd = read_field_csv(path)
    return fd.ids, np.asarray(fd.positions)


def find_tower_file(paint_dir: str | os.PathLike) -> Path:
    """The ``*-tower-measurements.json`` of a PAINT download directory.

    Raises:
        TypeError, ValueError: ``paint_dir`` is no path or empty
            (:func:`heliojax._io.check_path_argument`; None had searched the working
            directory).
        DataError: ``paint_dir`` is no directory, or holds no tower file.
    """
    check_path_argument(paint_dir, "paint_dir")
    if not os.path.isdir(paint_dir):  # a missing folder or a file had "no tower file in the PAINT directory"
        what = "a file" if os.path.exists(paint_dir) else "missing"
        raise DataError(paint_dir, None, f"not a directory ({what}): expected a PAINT download directory")
    # root_dir: the folder's own name is no pattern (one named "run[1]" had no tower file)
    hits = sorted(glob.glob("*" + TOWER_FILE_SUFFIX, root_dir=paint_dir))
    if not hits:
        raise DataError(paint_dir, None, "no *-tower-measurements.json in the PAINT directory")
    return Path(paint_dir) / hits[0]


def positions_from_paint(paint_dir: str | os.PathLike) -> tuple[tuple[str, ...], np.ndarray]:
    """Heliostat positions (ENU m) from a PAINT download directory: every heliostat
    folder's properties file (read by :mod:`heliojax.paint`), converted to ENU about
    the tower file's plant reference point."""
    tower = read_tower(find_tower_file(paint_dir))
    ids, lla = [], []
    for rel in sorted(glob.glob(os.path.join("*", "Properties", "*-heliostat-properties.json"), root_dir=paint_dir)):
        prop = Path(paint_dir) / rel
        props = read_heliostat_properties(prop)
        ids.append(props.heliostat_id)
        lla.append(props.position_lla)
    if not ids:
        raise DataError(paint_dir, None, "no heliostat properties files found")
    enu = np.asarray(wgs84_to_enu(jnp.asarray(np.asarray(lla)), jnp.asarray(tower.origin_lla)))
    return tuple(ids), enu


def field_from_summary(
    summary_path: str | os.PathLike,
    ids: tuple[str, ...],
    positions: np.ndarray,
    *,
    positions_from: str | None = None,
) -> FieldData:
    """Field of the heliostats ``ids`` (positions ENU m) with the tracking errors of
    ``summary.json``; heliostats of the summary without a position are an error, which
    names ``positions_from`` (where ``ids`` and ``positions`` were read, e.g.
    ``"--positions pos.csv"``) when given."""
    track = read_summary(summary_path)
    missing = sorted(set(track) - set(ids))
    if missing:
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise DataError(
            summary_path,
            f"heliostats.{missing[0]}",
            f"no position known for this heliostat{more}: {positions_from} has none"
            if positions_from is not None
            else "no position known for this heliostat (give --positions or --paint)",
        )
    values = np.array([track.get(h, math.nan) for h in ids])
    return FieldData(ids=tuple(ids), positions=np.asarray(positions, dtype=float), values={"tracking_mrad": values})


@dataclasses.dataclass(frozen=True)
class ParameterSpec:
    """Contract values of one parameter (its unit, see ``PARAMETERS``)."""

    mean: float
    std: float
    rel_error: float


@dataclasses.dataclass(frozen=True)
class Contract:
    """An acceptance contract (``configs/contract.toml``).

    Attributes:
        parameters: name -> :class:`ParameterSpec`.
        confidence, formula, z: sampling settings (:func:`sample_size`).
        clusters: keyword settings for clustering (``eps``, ``min_samples``,
            ``value_factor``, ``length_factor``, ``z_threshold``, ``k_neighbours``).
        bandwidth: KDE bandwidth (``"cv"``, ``"scott"``, ``"silverman"`` or a number).
        seed: random seed (bootstrap, KDE draws, contract scenario).
        tower_file: receiver/tower file, resolved against the contract's folder
            (None: not given).
        year, step_minutes, min_elevation_deg, sun_sigma_mrad: level-2 settings.
        tolerance: accepted relative shortfall of the measured annual efficiency.
        source: the contract file it was read from (None: built in code), named in messages.
    """

    parameters: dict[str, ParameterSpec]
    confidence: float = 0.95
    formula: str = "eq7"
    z: float | None = None
    clusters: dict = dataclasses.field(default_factory=dict)
    bandwidth: str | float = "cv"
    seed: int = 0
    tower_file: Path | None = None
    year: int = 2023
    step_minutes: float = 30.0
    min_elevation_deg: float = 5.0
    sun_sigma_mrad: float = 2.51
    tolerance: float = 0.0
    source: Path | None = None


MIN_CONFIDENCE = 0.5
MAX_CONFIDENCE = 0.999999
"""The contract's two-sided confidence level lies in this range: below one half an
interval holds the truth less often than not, above ``1 - 1e-6`` ``z`` (4.9) and the
sample size stop meaning anything for a field of heliostats."""

_CLUSTER_KEYS = {"eps", "min_samples", "value_factor", "length_factor", "z_threshold", "k_neighbours"}
_SECTION_KEYS = {
    "sampling": {"formula", "confidence", "z"},
    "extrapolation": {"bandwidth", "seed"},
    "yield": {"tower_file", "year", "step_minutes", "min_elevation_deg", "sun_sigma_mrad", "tolerance"},
}
"""Keys of the contract's plain sections ([parameters] and [clusters] are checked on their own)."""


def load_contract(path: str | os.PathLike) -> Contract:
    """Read and validate a contract TOML file (see ``configs/contract.toml``).

    Raises:
        TypeError, ValueError: ``path`` is no path (an int, None) or empty
            (:func:`heliojax._io.check_path_argument`).
        ConfigError: unreadable file (not a regular file: a FIFO blocked the read),
            unknown sections/keys, bad values.
    """
    check_path_argument(path)
    path = Path(path)
    try:
        problem = input_file_problem(path)
        if problem is not None:
            raise ConfigError(f"{path}: cannot read contract: {problem}")
        doc = tomllib.loads(path.read_text("utf-8"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read contract: {e}") from e
    except RecursionError:  # tomllib recurses once per level of nested arrays or tables
        raise ConfigError(f"{path}: malformed TOML: nested too deep") from None
    unknown = set(doc) - {"sampling", "parameters", "clusters", "extrapolation", "yield"}
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {sorted(unknown)}")
    for section, value in doc.items():
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: [{section}] must be a table, got {value!r}")
        extra = set(value) - _SECTION_KEYS.get(section, set(value))
        if extra:  # a misspelt key would silently leave its default in force
            raise ConfigError(
                f"{path}: [{section}] unknown key(s) {sorted(extra)}; known: {sorted(_SECTION_KEYS[section])}"
            )

    def num(sec, key, default=None, positive=False, low=-math.inf, high=math.inf, integer=False):
        table = doc.get(sec, {})
        if key not in table:
            if default is None:
                raise ConfigError(f"{path}: [{sec}] {key} is required")
            return default
        x = table[key]
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise ConfigError(f"{path}: [{sec}] {key} must be a finite number, got {x!r}")
        if integer and x != int(x):
            raise ConfigError(f"{path}: [{sec}] {key} must be an integer, got {x!r}")
        if positive and x <= 0:
            raise ConfigError(f"{path}: [{sec}] {key} must be > 0, got {x}")
        if not low <= x <= high:
            raise ConfigError(f"{path}: [{sec}] {key} must lie in {'(0' if positive else f'[{low}'}, {high}], got {x}")
        return x

    params = {}
    for name, spec in doc.get("parameters", {}).items():
        if name not in PARAMETERS:
            raise ConfigError(f"{path}: unknown parameter {name!r}; known: {sorted(PARAMETERS)}")
        if not isinstance(spec, dict) or set(spec) - {"mean", "std", "rel_error"}:
            raise ConfigError(f"{path}: [parameters.{name}] takes mean, std, rel_error")
        sec = f"parameters.{name}"
        vals = {}
        for key in ("mean", "std", "rel_error"):
            x = spec.get(key)
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x <= 0:
                raise ConfigError(f"{path}: [{sec}] {key} must be a number > 0, got {x!r}")
            if key in ("mean", "std") and name in PARAMETERS and x > PARAMETERS[name].maximum:
                unit = "" if PARAMETERS[name].unit == "1" else f" {PARAMETERS[name].unit}"  # "1": a fraction
                raise ConfigError(
                    f"{path}: [{sec}] {key} must be at most {PARAMETERS[name].maximum:g}{unit}, got {x!r}"
                )
            if key == "rel_error" and x >= 1:
                raise ConfigError(f"{path}: [{sec}] rel_error must be below 1 (a fraction of the mean), got {x!r}")
            vals[key] = float(x)
        # the sample size uses (std / (rel_error x mean))^2, the gamma model (mean / std)^2
        try:
            ratios = ((vals["std"] / (vals["rel_error"] * vals["mean"])) ** 2, (vals["mean"] / vals["std"]) ** 2)
        except (OverflowError, ZeroDivisionError):
            ratios = (math.inf, math.inf)
        if not all(math.isfinite(r) and r > 0 for r in ratios):
            raise ConfigError(
                f"{path}: [{sec}] mean {vals['mean']!r}, std {vals['std']!r} and rel_error {vals['rel_error']!r} are "
                "too far apart: (std / (rel_error x mean))^2 and (mean / std)^2 must be finite numbers above 0"
            )
        params[name] = ParameterSpec(**vals)
    if "tracking_mrad" not in params:
        raise ConfigError(f"{path}: [parameters.tracking_mrad] is required (level 2 needs it)")
    sampling = doc.get("sampling", {})
    formula = sampling.get("formula", "eq7")
    if formula not in ("eq4", "eq7", "eq8"):
        raise ConfigError(f"{path}: [sampling] formula must be eq4, eq7 or eq8, got {formula!r}")
    confidence = num("sampling", "confidence", 0.95)
    if not MIN_CONFIDENCE <= confidence <= MAX_CONFIDENCE:
        raise ConfigError(
            f"{path}: [sampling] confidence must lie in [{MIN_CONFIDENCE:g}, {MAX_CONFIDENCE:g}] (a two-sided "
            f"confidence level, e.g. 0.95), got {confidence!r}"
        )
    clusters = dict(doc.get("clusters", {}))
    if set(clusters) - _CLUSTER_KEYS:
        raise ConfigError(f"{path}: [clusters] unknown key(s) {sorted(set(clusters) - _CLUSTER_KEYS)}")
    for k in clusters:
        counts = k in ("min_samples", "k_neighbours")
        num("clusters", k, positive=True, high=10_000 if counts else 1e6, integer=counts)
    ex = doc.get("extrapolation", {})
    bandwidth = ex.get("bandwidth", "cv")
    if not (
        bandwidth in ("cv", "scott", "silverman")
        or (isinstance(bandwidth, (int, float)) and not isinstance(bandwidth, bool) and 0 < bandwidth <= 100)
    ):
        raise ConfigError(f"{path}: [extrapolation] bandwidth must be cv, scott, silverman or a factor in (0, 100]")
    y = doc.get("yield", {})
    tower = y.get("tower_file")
    if tower is not None and not isinstance(tower, str):
        raise ConfigError(f"{path}: [yield] tower_file must be a string")
    if tower is not None:
        where = (path.parent / tower).resolve()
        if where.is_dir():
            raise ConfigError(f"{path}: [yield] tower_file {tower!r} is a directory, not a tower file")
        if where.exists() and not where.is_file():  # a device (/dev/zero), a FIFO: read forever or never
            raise ConfigError(f"{path}: [yield] tower_file {tower!r} exists and is not a regular file")
        if not where.is_file():
            raise ConfigError(f"{path}: [yield] tower_file {tower!r} not found (relative to the contract's folder)")
    return Contract(
        parameters=params,
        confidence=float(confidence),
        formula=formula,
        z=None if "z" not in sampling else float(num("sampling", "z", positive=True, high=10.0)),
        clusters=clusters,
        bandwidth=bandwidth,
        seed=int(num("extrapolation", "seed", 0, low=0, high=2**32 - 1, integer=True)),
        tower_file=None if tower is None else (path.parent / tower).resolve(),
        source=Path(path),
        year=int(num("yield", "year", 2023, low=1900, high=2200, integer=True)),
        step_minutes=float(num("yield", "step_minutes", 30.0, low=1.0, high=1440.0)),
        min_elevation_deg=float(num("yield", "min_elevation_deg", 5.0, low=0.0, high=89.0)),
        sun_sigma_mrad=float(num("yield", "sun_sigma_mrad", 2.51, positive=True, high=100.0)),
        tolerance=float(num("yield", "tolerance", 0.0, low=0.0, high=0.99)),
    )
