"""The load report's log and the checks that flag suspicious inputs (robust outlier
rule, the actuator law against its declared range, repeated weather)."""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence

import numpy as np

from .._errors import DataError
from .._fleet import MIN_FLEET_FOR_OUTLIERS, OUTLIER_FLOOR, OUTLIER_K, LoadReport, ReportEntry
from .._sun import datetime_to_unix
from ._common import (
    MAX_HELIOSTAT_HEIGHT_M,
    WEATHER_KEYS,
    CalibrationRecord,
    HeliostatProperties,
)


class _Log:
    """Mutable collector behind a :class:`LoadReport`."""

    def __init__(self, source: str, strict: bool, centroid: str):
        self.source = source
        self.strict = strict
        self.centroid = centroid
        self.files_seen = 0
        self.records_skipped = 0
        self.heliostats_skipped = 0
        self.skipped: list[ReportEntry] = []
        self.flags: list[ReportEntry] = []
        self.notes: list[str] = []

    def skip(self, err: DataError, records: int = 0, heliostats: int = 0) -> None:
        if self.strict:
            raise err
        self.skipped.append(ReportEntry(str(err.file), err.field, err.reason, heliostats > 0))
        self.records_skipped += records
        self.heliostats_skipped += heliostats

    def skip_record(self, err: DataError) -> None:
        self.skip(err, records=1)

    def skip_entry(self, err: DataError) -> None:
        self.skip(err)

    def flag(self, file: str, field: str | None, reason: str) -> None:
        self.flags.append(ReportEntry(str(file), field, reason))

    def report(self, **counts) -> LoadReport:
        return LoadReport(
            source=self.source,
            files_seen=self.files_seen,
            records_skipped=self.records_skipped,
            heliostats_skipped=self.heliostats_skipped,
            centroid=self.centroid,
            skipped=tuple(self.skipped),
            flags=tuple(self.flags),
            notes=tuple(self.notes),
            **counts,
        )


# ======================================================================================
# Fleet
# ======================================================================================


def _actuator_law(*args):
    inc, s0, a, b, ang0, sign, counts = args
    return ang0 + sign * (_actuator_psi(counts / inc + s0, a, b) - _actuator_psi(s0, a, b))


def _actuator_psi(s, a, b):
    with np.errstate(all="ignore"):  # an absurd stroke saturates (flagged); no warning on stderr
        return np.arccos(np.clip((a**2 + b**2 - s**2) / (2 * a * b), -1.0, 1.0))


def _law_at_limits(a: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The counts-to-angle law of the actuator(s) ``a`` (PAINT keys; numbers or arrays,
    elementwise) at its two count limits and its mean slope: ``(lo, hi, slope)``."""
    with np.errstate(all="ignore"):
        args = [
            np.asarray(a[k], np.float64)
            for k in ("increment", "initial_stroke_length", "offset", "pivot_radius", "initial_angle")
        ]
        sign = np.where(np.asarray(a["clockwise_axis_movement"]) == 0, 1.0, -1.0)
        lo, hi = (_actuator_law(*args, sign, np.asarray(a[k], np.float64)) for k in ("min_increment", "max_increment"))
        slope = (hi - lo) / (np.asarray(a["max_increment"], np.float64) - np.asarray(a["min_increment"], np.float64))
    return np.asarray(lo), np.asarray(hi), np.asarray(slope)


def _law_kept(lo: np.ndarray, hi: np.ndarray, slope: np.ndarray) -> np.ndarray:
    return np.asarray(np.isfinite(lo) & np.isfinite(hi) & np.isfinite(slope) & (slope != 0))


def actuator_law_kept(a: dict) -> np.ndarray:
    """Elementwise over the actuator(s) ``a`` (PAINT keys, numbers or arrays): whether
    :func:`actuator_law_problem` finds nothing."""
    return _law_kept(*_law_at_limits(a))


def actuator_law_problem(a: dict) -> str | None:
    """Why the counts-to-angle law of the actuator ``a`` (PAINT keys) gives no finite,
    distinct angles at its two count limits, or None when it does."""
    lo, hi, slope = _law_at_limits(a)
    if _law_kept(lo, hi, slope):
        return None
    return (
        f"the actuator law gives no usable angle range over [min_increment, max_increment] "
        f"(angles {float(lo)!r} .. {float(hi)!r} rad)"
    )


def _check_actuator_law(p: HeliostatProperties) -> None:
    """The counts-to-angle law must give finite, distinct angles at both count limits."""
    for i, a in enumerate(p.actuators):
        problem = actuator_law_problem(a)
        if problem is not None:
            raise DataError(p.source, f"kinematics_properties.actuators[{i}]", problem)


def _flag_unmodelled_actuator_keys(props: list[HeliostatProperties], log: _Log) -> None:
    """Flags the optional actuator keys that say something heliojax's kinematics do not
    model, so that their values would be ignored without a word: a non-zero
    ``offset_shift`` or ``radius_shift`` (the actuator triangle is taken as ``offset``
    and ``pivot_radius``; a calibration absorbs a small shift in its stroke offsets), and
    a movement-angle range whose minimum exceeds its maximum (no command is limited by
    it)."""
    for p in props:
        for i, act in enumerate(p.actuators):
            field = f"kinematics_properties.actuators[{i}]"
            for key in ("offset_shift", "radius_shift"):
                value = act.get(key)
                if isinstance(value, (int, float)) and not isinstance(value, bool) and value != 0:
                    log.flag(
                        p.source,
                        f"{field}.{key}",
                        f"{float(value):.6g} m is not modelled: heliojax takes the actuator triangle "
                        "from offset and pivot_radius and ignores the shift (nominal errors will show it)",
                    )
            lo, hi = act.get("min_movement_angle"), act.get("max_movement_angle")
            numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (lo, hi))
            if numbers and float(lo) > float(hi):  # pyright: ignore[reportArgumentType]
                log.flag(
                    p.source,
                    f"{field}.min_movement_angle",
                    f"{float(lo):.6g} rad exceeds max_movement_angle {float(hi):.6g} rad (swapped?)",  # pyright: ignore[reportArgumentType]
                )


CLOSE_PAIRS_BY_TREE = 1024
"""From this many points on, :func:`close_pairs` searches a k-d tree (scipy's, imported
then: ~0.1 s of a command's start); below, all pairs at once in NumPy."""


def close_pairs(xy: np.ndarray, reach: float) -> list[tuple[int, int]]:
    """The pairs ``(i, j)``, ``i < j``, of the ``(N, 2)`` points ``xy`` at most ``reach``
    apart (same units), sorted: by all ``N (N - 1) / 2`` distances at once below
    :data:`CLOSE_PAIRS_BY_TREE` points, else by :class:`scipy.spatial.KDTree`."""
    n = len(xy)
    if n >= CLOSE_PAIRS_BY_TREE:
        from scipy.spatial import KDTree

        return sorted(KDTree(xy).query_pairs(reach))
    i, j = np.triu_indices(n, k=1)
    near = np.linalg.norm(xy[i] - xy[j], axis=1) <= reach
    return [(int(a), int(b)) for a, b in zip(i[near], j[near], strict=True)]


def _flag_overlapping(props: list[HeliostatProperties], log: _Log) -> None:
    """Flag pairs of heliostats whose mirrors would overlap in any pose: centres
    closer than the sum of half their shorter sides (a properties file copied with its
    position edited; exact duplicates of a position are skipped elsewhere). East and north
    come from a local tangent plane at the first heliostat, in NumPy float64 (a field's
    extent makes its error negligible at these centimetres), not from
    :func:`heliojax.wgs84_to_enu`, which runs in JAX's default dtype: float32 without
    x64, half a metre at ECEF magnitudes."""
    if len(props) < 2:
        return
    lla = np.radians(np.array([p.position_lla[:2] for p in props], float))  # (H, 2) lat, lon
    xy = 6_371_000.0 * np.stack([lla[:, 1] * math.cos(lla[0, 0]), lla[:, 0]], axis=1)  # east, north (m)
    half = np.array([min(p.width, p.height) for p in props], float) / 2.0
    for i, j in close_pairs(xy, float(2.0 * half.max())):
        gap = float(np.linalg.norm(xy[i] - xy[j]))
        if gap < half[i] + half[j]:
            log.flag(
                props[j].source,
                "heliostat_position",
                f"{gap:.3g} m from heliostat {props[i].heliostat_id!r}: their mirrors would overlap (a "
                "properties file copied with its position edited?)",
            )


def _flag_properties(props: list[HeliostatProperties], log: _Log) -> None:
    """Physics checks per heliostat and robust fleet-outlier flags (module docstring)."""
    n = len(props)
    if n == 0:
        return
    _flag_unmodelled_actuator_keys(props, log)
    _flag_overlapping(props, log)
    a = {
        k: np.array([[float(p.actuators[i][k]) for i in range(2)] for p in props])
        for k in (
            "increment",
            "initial_stroke_length",
            "offset",
            "pivot_radius",
            "initial_angle",
            "min_increment",
            "max_increment",
            "clockwise_axis_movement",
        )
    }
    sign = np.where(a["clockwise_axis_movement"] == 0, 1.0, -1.0)
    # Triangle feasibility over the count range (stroke is monotone in the counts).
    for end in ("min_increment", "max_increment"):
        stroke = a[end] / a["increment"] + a["initial_stroke_length"]
        lo = np.abs(a["offset"] - a["pivot_radius"])
        hi = a["offset"] + a["pivot_radius"]
        bad = (stroke < lo) | (stroke > hi)
        for h, i in zip(*np.nonzero(bad)):
            log.flag(
                props[h].source,
                f"kinematics_properties.actuators[{i}].initial_stroke_length",
                f"stroke {stroke[h, i]:.4g} m at {end} = {a[end][h, i]:.8g} lies outside the actuator "
                f"triangle [{lo[h, i]:.4f}, {hi[h, i]:.4f}] m (law of cosines saturates)",
            )
    # Majority direction of motion.
    for i in range(2):
        vals = a["clockwise_axis_movement"][:, i]
        cnt = collections.Counter(vals.tolist())
        mode, k = cnt.most_common(1)[0]
        if n >= MIN_FLEET_FOR_OUTLIERS and 2 * k > n:
            for h in np.nonzero(vals != mode)[0]:
                log.flag(
                    props[h].source,
                    f"kinematics_properties.actuators[{i}].clockwise_axis_movement",
                    f"{int(vals[h])} where {k} of {n} heliostats have {int(mode)}",
                )
    if n < MIN_FLEET_FOR_OUTLIERS:
        log.notes.append(f"actuator outlier check not run: {n} heliostat(s) (needs {MIN_FLEET_FOR_OUTLIERS})")
        return
    span = np.abs(
        _actuator_law(
            a["increment"],
            a["initial_stroke_length"],
            a["offset"],
            a["pivot_radius"],
            a["initial_angle"],
            sign,
            a["max_increment"],
        )
        - _actuator_law(
            a["increment"],
            a["initial_stroke_length"],
            a["offset"],
            a["pivot_radius"],
            a["initial_angle"],
            sign,
            a["min_increment"],
        )
    )
    checks: list[tuple[str, np.ndarray, np.ndarray, str]] = []  # (field, values (n,), scale (), unit)
    for i in range(2):
        for k, unit in (
            ("increment", "counts/m"),
            ("initial_stroke_length", "m"),
            ("offset", "m"),
            ("pivot_radius", "m"),
        ):
            v = a[k][:, i]
            checks.append((f"kinematics_properties.actuators[{i}].{k}", v, abs(np.median(v)), unit))
        checks.append(
            (
                f"kinematics_properties.actuators[{i}].initial_angle",
                a["initial_angle"][:, i],
                np.median(span[:, i]),
                "rad",
            )
        )
    width = np.median([p.width for p in props])
    for key in ("width", "height"):  # a mirror of 5e-324 m is no heliostat (the size bounds only cap it)
        sizes = np.array([getattr(p, key) for p in props])
        checks.append((key, sizes, np.median(sizes), "m"))  # pyright: ignore[reportArgumentType]
    for name, attr in (
        ("joint_translation_{}_1", "joint_translation_1"),
        ("joint_translation_{}_2", "joint_translation_2"),
        ("concentrator_translation_{}", "concentrator_translation"),
    ):
        vals = np.array([getattr(p, attr) for p in props])
        for j, c in enumerate("enu"):
            checks.append((f"kinematics_properties.{name.format(c)}", vals[:, j], width, "m"))  # pyright: ignore[reportArgumentType]
    # an altitude from another datum, in feet, or 0 for unknown puts a heliostat tens of
    # metres above or below its neighbours (the floor: 5 x 0.01 x 1000 m = 50 m)
    altitudes = np.array([p.position_lla[2] for p in props])
    checks.append(("heliostat_position", altitudes, MAX_HELIOSTAT_HEIGHT_M, "m altitude"))  # pyright: ignore[reportArgumentType]
    for field, v, scale, unit in checks:
        for h, reason in fleet_outliers(v, float(scale), unit):
            log.flag(props[h].source, field, reason)


def fleet_outliers(v: np.ndarray, scale: float, unit: str) -> list[tuple[int, str]]:
    """The robust outlier rule of the load's fleet checks: ``(index, reason)`` of each
    value of ``v`` (one per heliostat) farther than ``OUTLIER_K x max(1.4826 MAD,
    OUTLIER_FLOOR x scale)`` from the fleet median (shared by the properties reader and
    ``load_results``; empty below ``MIN_FLEET_FOR_OUTLIERS`` heliostats)."""
    v = np.asarray(v, float)
    if v.size < MIN_FLEET_FOR_OUTLIERS:
        return []
    med = np.median(v)
    mad = np.median(np.abs(v - med))
    thr = OUTLIER_K * max(1.4826 * mad, OUTLIER_FLOOR * scale)
    return [
        (
            int(h),
            f"{v[h]:.6g} {unit} is far from the fleet median {med:.6g} "
            f"(|dev| {abs(v[h] - med):.3g} > {thr:.3g} = {OUTLIER_K:g} x max(1.4826 MAD, "
            f"{OUTLIER_FLOOR:g} x scale))",
        )
        for h in np.nonzero(np.abs(v - med) > thr)[0]
    ]


EARLIEST_RECORD_TIME = 946684800.0
"""2000-01-01T00:00:00Z: earlier record times are flagged (PAINT's records start in 2021)."""


def _flag_weather_gaps(rows: Sequence[CalibrationRecord], file: str, log: _Log) -> None:
    """Flag weather variables no row knows (a missing or empty column) and records
    listed twice with different weather (the later row is used)."""
    if not rows:
        return
    for key in WEATHER_KEYS:
        if all(math.isnan(r.weather[key]) for r in rows):
            log.flag(file, key, f"no row has a {key} (column missing or empty): unknown for every record")
    seen: dict[tuple[str, int], dict[str, float]] = {}
    for r in rows:
        key = (r.heliostat_id, r.record_id)
        old = seen.get(key)
        if old is not None and any(
            not (math.isnan(old[k]) and math.isnan(r.weather[k])) and old[k] != r.weather[k] for k in WEATHER_KEYS
        ):
            log.flag(
                file, f"{r.heliostat_id}.{r.record_id}", "listed twice with different weather: the later row is used"
            )
        seen[key] = r.weather


def _flag_repeated_weather(records: Sequence[CalibrationRecord], file: str, log: _Log) -> None:
    """Flag weather tuples repeated over rows spanning more than an hour (forward fill)."""
    groups: dict[tuple, list[float]] = collections.defaultdict(list)
    for r in records:
        w = tuple(r.weather[k] for k in ("temperature", "wind_speed", "wind_direction", "dni", "humidity", "pressure"))
        if all(math.isfinite(x) for x in w) and r.datetime is not None:
            groups[w].append(datetime_to_unix(r.datetime))
    for w, ts in groups.items():
        hours = (max(ts) - min(ts)) / 3600.0
        if len(ts) >= 3 and hours > 1.0:
            log.flag(
                file,
                "weather",
                f"identical weather (temperature, wind_speed, wind_direction, dni, humidity, pressure) "
                f"= {w} on {len(ts)} rows spanning {hours:.1f} h: looks forward-filled",
            )
