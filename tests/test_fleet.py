"""Tests of heliojax._fleet: assembly, loaders, report, padding.

Reference values are counted independently from the files (json/csv modules,
numpy), or follow from physics (focal spots lie on their target plane, the sun
vector of the PAINT convention written out in numpy).
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import heliojax as hj
from heliojax._errors import DataError
from heliojax._fleet import (
    OUTLIER_FLOOR,
    OUTLIER_K,
    Fleet,
    LoadReport,
    bucket_size,
    fleet_subset,
    pad_fleet,
)
from heliojax.paint import (
    CalibrationRecord,
    default_data_dir,
    load_paint_directory,
    load_weather_csv_fleet,
    read_calibration_record,
    read_heliostat_properties,
    read_timestamps,
    read_tower,
    read_weather_csv,
    records_to_fleet,
    write_paint_directory,
)

EMB = default_data_dir()
EMB_IDS = ("BE36", "BF56", "BG23", "BH20", "BL14")


@pytest.fixture(scope="module")
def emb_fleet() -> Fleet:
    return load_paint_directory()


@pytest.fixture(scope="module")
def shared_fleet(shared_paint) -> Fleet:
    return load_paint_directory(shared_paint)


@pytest.fixture(scope="module")
def raw_emb():
    tower = read_tower(EMB / "WRI1030197-tower-measurements.json")
    ts = read_timestamps(EMB / "calibration-timestamps.json")
    weather = {(r.heliostat_id, r.record_id): r.weather for r in read_weather_csv(EMB / "calibration-with-weather.csv")}
    props = [read_heliostat_properties(f) for f in sorted(EMB.glob("*/Properties/*.json"))]
    recs = [
        read_calibration_record(f, timestamps=ts, weather=weather) for f in sorted(EMB.glob("*/Calibration/*.json"))
    ]
    return tower, props, recs


def _valid(fleet: Fleet, hid: str) -> dict[str, np.ndarray]:
    """The valid-record arrays of one heliostat (plus its geometry), as numpy."""
    h = fleet.heliostat(hid)
    m = np.asarray(h.mask)
    out = {
        "counts": np.asarray(h.counts)[m],
        "focal_spot": np.asarray(h.focal_spot)[m],
        "target_index": np.asarray(h.target_index)[m],
        "record_id": np.asarray(h.record_id)[m],
    }
    for k, v in vars(h.context).items():
        out[f"context.{k}"] = np.asarray(v)[m]
    for i, leaf in enumerate(jax.tree.leaves(h.geometry)):
        out[f"geometry.{i}"] = np.asarray(leaf)
    return out


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)


def _leaves_equal(a, b) -> bool:
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(la) == len(lb) and all(
        x.shape == y.shape and x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True) for x, y in zip(la, lb)
    )


# --------------------------------------------------------------------------------------
# Embedded data
# --------------------------------------------------------------------------------------


def test_embedded_data(emb_fleet):
    f = emb_fleet
    assert f.ids == EMB_IDS
    assert (EMB / "NOTICE").read_text().count("CDLA-Permissive-2.0") >= 1
    assert "https://cdla.dev/permissive-2-0/" in (EMB / "NOTICE").read_text()
    n_files = {h: len(list((EMB / h / "Calibration").glob("*-calibration-properties.json"))) for h in EMB_IDS}
    assert n_files == {"BE36": 164, "BF56": 137, "BG23": 52, "BH20": 30, "BL14": 9}
    assert np.asarray(f.mask).sum(1).tolist() == [n_files[h] for h in EMB_IDS]
    assert (f.n_heliostats, f.n_records) == (5, 164)
    assert f.counts.dtype == jnp.float64 and f.mask.dtype == jnp.bool_
    r = f.report
    assert (r.records_loaded, r.records_skipped, r.heliostats_loaded, r.heliostats_skipped) == (392, 0, 5, 0)
    assert r.files_seen == 3 + 5 + 392 and r.skipped == () and r.flags == ()
    assert r.records_with_weather == 100  # the CSV rows of BE36 and BF56


def test_fleet_values_against_physics(emb_fleet):
    f = emb_fleet
    m = np.asarray(f.mask)
    # Sun vector written out (PAINT: azimuth from south, positive toward east).
    h = f.index("BE36")
    j = int(np.nonzero(np.asarray(f.record_id[h]) == 118671)[0][0])
    az, el = np.deg2rad(-48.91974860208279), np.deg2rad(54.66615202629741)
    expect = [np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)]
    np.testing.assert_allclose(np.asarray(f.context.sun[h, j]), expect, rtol=0, atol=1e-15)
    assert np.asarray(f.counts[h, j]).tolist() == [45501.0, 53811.0]
    assert f.target_names[int(f.target_index[h, j])] == "solar_tower_juelich_lower"
    # Every focal spot lies on its target plane (built from the corners) within 5 cm.
    c = np.asarray(f.targets.centre)[np.asarray(f.target_index)]
    n = np.asarray(f.targets.normal)[np.asarray(f.target_index)]
    d = np.einsum("hmk,hmk->hm", np.asarray(f.focal_spot) - c, n)
    assert np.abs(d[m]).max() < 0.05
    # The surveyed corners give planes within 6 mrad of the nominal north normal.
    np.testing.assert_allclose(np.asarray(f.targets.normal), [[0, 1, 0]] * 3, atol=6e-3)
    # Heliostats stand north of the tower at about ground level; the row letter of the
    # id (BE, BF, BG, BH, BL) grows with the distance to the north.
    pos = np.asarray(f.geometry.position)
    assert np.all((pos[:, 1] > 25) & (pos[:, 1] < 350)) and np.all(np.abs(pos[:, 2]) < 5)
    assert np.all(np.diff(pos[:, 1]) > 5)
    # Actuator signs from clockwise_axis_movement (0 -> +1 on axis 1, 1 -> -1 on axis 2).
    assert np.asarray(f.geometry.actuators.sign).tolist() == [[1.0, -1.0]] * 5
    assert np.asarray(f.origin_lla).tolist() == [50.913421122592574, 6.387824755874856, 87.0]


def test_chronological_order_and_time(emb_fleet):
    f = emb_fleet
    ts = read_timestamps(EMB / "calibration-timestamps.json")
    t = np.asarray(f.context.unix_time)
    m = np.asarray(f.mask)
    for h in range(f.n_heliostats):
        th = t[h][m[h]]
        assert np.all(np.isfinite(th)) and np.all(np.diff(th) >= 0)
        ids = np.asarray(f.record_id[h])[m[h]]
        assert sorted(ids.tolist()) == sorted(k for k, e in ts.items() if e.heliostat_id == f.ids[h])
    # 2022-06-12T13:27:37Z is 1655040457 s after the epoch (calendar.timegm).
    h = f.index("BE36")
    j = int(np.nonzero(np.asarray(f.record_id[h]) == 118671)[0][0])
    assert float(t[h, j]) == 1655040457.0


def test_weather_join(emb_fleet):
    f = emb_fleet
    rows = {(r.heliostat_id, r.record_id): r.weather for r in read_weather_csv(EMB / "calibration-with-weather.csv")}
    temp = np.asarray(f.context.temperature)
    wdir = np.asarray(f.context.wind_direction)
    rid = np.asarray(f.record_id)
    m = np.asarray(f.mask)
    n = 0
    for h, hid in enumerate(f.ids):
        for j in np.nonzero(m[h])[0]:
            w = rows.get((hid, int(rid[h, j])))
            if w is None:
                assert math.isnan(temp[h, j]) and math.isnan(wdir[h, j])
            else:
                n += 1
                assert temp[h, j] == w["temperature"]
                assert wdir[h, j] == pytest.approx(math.radians(w["wind_direction"]), abs=1e-15)
    assert n == 100


def _sun_at(when: str, lla) -> dict[str, float]:
    """The sun of a record at ``when`` seen from ``lla`` (the loader skips any other)."""
    with jax.enable_x64(True):
        pos = hj.solar_position(hj.datetime_to_unix(when), *lla)
    return {"sun_azimuth_deg": math.degrees(pos.azimuth), "sun_elevation_deg": math.degrees(pos.elevation)}


def test_approach_by_hand(raw_emb):
    tower, props, _ = raw_emb
    p = next(p for p in props if p.heliostat_id == "BL14")
    base = dict(
        heliostat_id="BL14",
        target_name="solar_tower_juelich_lower",
        sun_azimuth_deg=10.0,
        sun_elevation_deg=40.0,
        focal_spot_helios=(50.91339, 6.38782, 123.0),
    )
    # Chronology: ids 1..6 at increasing times except id 4, which has no time and is
    # placed by its id (between 3 and 5). Written in scrambled order.
    seq = [
        (1, 10, 500, "2023-01-01T10:00:00Z"),
        (2, 20, 500, "2023-01-01T11:00:00Z"),
        (3, 20, 500, "2023-01-01T12:00:00Z"),
        (4, 15, 400, None),
        (5, 15, 400, "2023-01-02T10:00:00Z"),
        (6, 30, 450, "2023-01-02T11:00:00Z"),
    ]
    recs = [CalibrationRecord(record_id=i, axis_1_counts=a, axis_2_counts=b, datetime=t, **base) for i, a, b, t in seq]
    recs = [r if r.datetime is None else dataclasses.replace(r, **_sun_at(r.datetime, p.position_lla)) for r in recs]
    f = records_to_fleet(tower, [p], recs[::-1])
    assert np.asarray(f.record_id[0]).tolist() == [1, 2, 3, 4, 5, 6]
    # Axis 1: 10 -> 20 (+), 20 (no move: keeps +), 15 (-), 15 (keeps -), 30 (+).
    # Axis 2: 500 (first moves at id 4: -), 400 (keeps -), 450 (+).
    assert np.asarray(f.context.approach[0]).tolist() == [[0, 0], [1, 0], [1, 0], [-1, -1], [-1, -1], [1, 1]]
    assert f.report.records_without_time == 1
    assert [(e.field, Path(e.file).name) for e in f.report.flags] == [("datetime", "<memory>")]


# --------------------------------------------------------------------------------------
# The shared download
# --------------------------------------------------------------------------------------


def test_shared_directory(shared_fleet, shared_paint):
    f = shared_fleet
    r = f.report
    with_props = sorted(p.parents[1].name for p in shared_paint.glob("*/Properties/*-heliostat-properties.json"))
    assert f.ids == tuple(with_props) and len(f.ids) == 27
    n_bg63 = len(list((shared_paint / "BG63" / "Calibration").glob("*.json")))
    n_all = len(list(shared_paint.glob("*/Calibration/*-calibration-properties.json")))
    assert (r.heliostats_loaded, r.heliostats_skipped) == (27, 1)
    assert (r.records_loaded, r.records_skipped) == (n_all - n_bg63, n_bg63) == (1604, 108)
    assert int(np.asarray(f.mask).sum()) == r.records_loaded
    assert len(r.skipped) == 1 and "BG63" in r.skipped[0].file and "no properties" in r.skipped[0].reason
    # Records without a timestamp: kept with NaN time, each flagged; counted independently.
    ts = read_timestamps(shared_paint / "calibration-timestamps.json")
    no_time = {
        int(p.name.split("-")[0]) for p in shared_paint.glob("*/Calibration/*.json") if p.parents[1].name != "BG63"
    } - set(ts)
    assert r.records_without_time == len(no_time) == 5
    t = np.asarray(f.context.unix_time)
    m = np.asarray(f.mask)
    assert set(np.asarray(f.record_id)[m & np.isnan(t)].tolist()) == no_time
    assert sum(e.field == "datetime" for e in r.flags) == 5
    # BF41's anomalous actuators are flagged (statistically and by the triangle check).
    bf41 = [e for e in r.flags if "BF41" in e.file]
    fields = {e.field for e in bf41}
    assert "kinematics_properties.actuators[0].initial_stroke_length" in fields
    assert "kinematics_properties.actuators[1].initial_stroke_length" in fields
    assert "kinematics_properties.actuators[1].initial_angle" in fields
    assert any("triangle" in e.reason for e in bf41)
    assert "BF41" in r.format() and "BG63" in r.format()
    # The forward-filled weather tuple of the CSV (215 rows, README) is flagged.
    assert any(e.field == "weather" and "215 rows" in e.reason for e in r.flags)


def test_outlier_rule_by_hand(shared_fleet, shared_paint):
    """Recompute the rule for initial_stroke_length of axis 2 independently."""
    vals = {}
    for p in shared_paint.glob("*/Properties/*-heliostat-properties.json"):
        actuators = json.loads(p.read_text())["kinematics_properties"]["actuators"]
        vals[p.parents[1].name] = actuators[1]["initial_stroke_length"]
    v = np.array(list(vals.values()))
    med = np.median(v)
    thr = OUTLIER_K * max(1.4826 * np.median(np.abs(v - med)), OUTLIER_FLOOR * med)
    expect = {h for h, x in vals.items() if abs(x - med) > thr}
    got = {
        Path(e.file).parents[1].name
        for e in shared_fleet.report.flags
        if e.field == "kinematics_properties.actuators[1].initial_stroke_length" and "median" in e.reason
    }
    assert got == expect and "BF41" in got


def test_centroid_selection(shared_fleet, shared_paint):
    f_u = shared_fleet
    f_h = load_paint_directory(shared_paint, centroid="helios")
    assert f_u.ids == f_h.ids
    assert np.array_equal(np.asarray(f_u.record_id), np.asarray(f_h.record_id))
    m = np.asarray(f_u.mask)
    helios_only = set()
    for p in shared_paint.glob("*/Calibration/*.json"):
        if p.parents[1].name != "BG63" and "UTIS" not in json.loads(p.read_text())["focal_spot"]:
            helios_only.add(int(p.name.split("-")[0]))
    assert f_u.report.centroid_fallbacks == len(helios_only) == 9
    assert f_h.report.centroid_fallbacks == 0 and f_h.report.centroid == "helios"
    fallback = m & np.isin(np.asarray(f_u.record_id), list(helios_only))
    both = m & ~fallback
    d = np.linalg.norm(np.asarray(f_u.focal_spot) - np.asarray(f_h.focal_spot), axis=-1)
    assert np.all(d[fallback] == 0.0)  # HeliOS in both modes
    assert np.all(d[both] > 0.0)
    # README: median UTIS-HeliOS distance 0.07 m, maximum 1.4 m.
    assert 0.03 < np.median(d[both]) < 0.15 and d[both].max() < 1.5
    # The selected centroid is the file's: check one record against the file by hand.
    h = f_u.index("BE36")
    j = int(np.nonzero(np.asarray(f_u.record_id[h]) == 118671)[0][0])
    from heliojax._geometry import wgs84_to_enu

    utis = wgs84_to_enu(jnp.asarray([50.9133920558005, 6.387820891167903, 122.98824310302734]), f_u.origin_lla)
    helios = wgs84_to_enu(jnp.asarray([50.91339203951505, 6.387820495303746, 123.0394382264574]), f_u.origin_lla)
    np.testing.assert_allclose(np.asarray(f_u.focal_spot[h, j]), np.asarray(utis), atol=1e-9)
    np.testing.assert_allclose(np.asarray(f_h.focal_spot[h, j]), np.asarray(helios), atol=1e-9)


def test_strict_and_filter(shared_paint, unchecked):
    with pytest.raises(DataError) as e:
        load_paint_directory(shared_paint, strict=True)
    assert e.value.file.endswith("BG63/Properties/BG63-heliostat-properties.json")
    f = load_paint_directory(shared_paint, heliostats=["BL14", "BF41", "ZZ99"])
    assert f.ids == ("BF41", "BL14")
    assert f.report.heliostats_skipped == 1 and "ZZ99" in f.report.skipped[0].reason
    with pytest.raises(ValueError):
        load_paint_directory(shared_paint, centroid="mean")


def test_csv_form(shared_paint):
    csv_path = shared_paint / "calibration-with-weather.csv"
    f = load_weather_csv_fleet(csv_path, shared_paint / "WRI1030197-tower-measurements.json")
    rows = read_weather_csv(csv_path)
    in_csv = {r.heliostat_id for r in rows}
    with_props = {p.parents[1].name for p in shared_paint.glob("**/Properties/*-heliostat-properties.json")}
    expect = sorted(in_csv & with_props)
    assert f.ids == tuple(expect) and len(expect) == 8
    r = f.report
    assert r.heliostats_skipped == len(in_csv) - len(expect) == 121
    assert r.records_loaded + r.records_skipped == len(rows) == 6057
    assert r.records_loaded == sum(x.heliostat_id in with_props for x in rows)
    assert {e.reason.split("'")[1] for e in r.skipped} == in_csv - with_props
    assert r.centroid_fallbacks == r.records_loaded  # the CSV carries HeliOS only
    m = np.asarray(f.mask)
    assert np.all(np.isfinite(np.asarray(f.context.temperature))[m])
    assert np.all(np.isfinite(np.asarray(f.context.unix_time))[m])
    # A record present in both forms gets the same counts, sun, time and HeliOS spot.
    d = load_paint_directory(shared_paint, centroid="helios", heliostats=["BE36"])
    a, b = f.heliostat("BE36"), d.heliostat("BE36")
    common = np.intersect1d(np.asarray(a.record_id)[np.asarray(a.mask)], np.asarray(b.record_id)[np.asarray(b.mask)])
    assert len(common) == 51
    for rid in common[:5]:
        i = int(np.nonzero(np.asarray(a.record_id) == rid)[0][0])
        k = int(np.nonzero(np.asarray(b.record_id) == rid)[0][0])
        for x, y in (
            (a.counts, b.counts),
            (a.focal_spot, b.focal_spot),
            (a.context.sun, b.context.sun),
            (a.context.unix_time, b.context.unix_time),
            (a.context.temperature, b.context.temperature),
        ):
            assert np.array_equal(np.asarray(x[i]), np.asarray(y[k]))


# --------------------------------------------------------------------------------------
# Bad input in a directory: skipped and reported, the others intact
# --------------------------------------------------------------------------------------


def _copy_emb(tmp_path) -> Path:
    d = tmp_path / "paint"
    shutil.copytree(EMB, d)
    return d


def _edit(path: Path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _first_bh20(d: Path) -> Path:
    return sorted((d / "BH20" / "Calibration").glob("*.json"))[0]


def _mut(field, value):
    def fn(data):
        obj = data
        keys = field.split(".")
        for k in keys[:-1]:
            obj = obj[k]
        if value is None:
            del obj[keys[-1]]
        else:
            obj[keys[-1]] = value

    return fn


BAD_RECORDS = [
    ("unknown target", _mut("target_name", "nowhere"), "target_name"),
    (
        "counts out of range",
        _mut("motor_position.axis_1_motor_position", 10**6),
        "motor_position.axis_1_motor_position",
    ),
    ("missing field", _mut("sun_azimuth", None), "sun_azimuth"),
    ("non-numeric", _mut("sun_elevation", "high"), "sun_elevation"),
    # (a NaN centroid is read as missing: tests/test_paint_versions.py)
    ("non-finite", _mut("sun_azimuth", float("nan")), "sun_azimuth"),
]


@pytest.mark.parametrize("name,fn,field", BAD_RECORDS, ids=[c[0] for c in BAD_RECORDS])
def test_bad_record_in_directory(tmp_path, emb_fleet, name, fn, field):
    d = _copy_emb(tmp_path)
    bad = _first_bh20(d)
    _edit(bad, fn)
    f = load_paint_directory(d)
    r = f.report
    assert f.ids == EMB_IDS
    assert (r.records_loaded, r.records_skipped, r.heliostats_skipped) == (391, 1, 0)
    assert r.skipped[0].file == str(bad) and r.skipped[0].field == field
    bad_id = int(bad.name.split("-")[0])
    assert bad_id not in np.asarray(f.heliostat("BH20").record_id).tolist()
    for hid in ("BE36", "BF56", "BG23", "BL14"):
        assert _same(_valid(f, hid), _valid(emb_fleet, hid)), hid
    with pytest.raises(DataError) as e:
        load_paint_directory(d, strict=True)
    assert (e.value.file, e.value.field) == (str(bad), field)


def test_bad_files_in_directory(tmp_path, emb_fleet):
    d = _copy_emb(tmp_path)
    # A malformed record of BH20, a broken properties file of BL14, records of a
    # heliostat without properties (XX01), a malformed timestamp entry.
    (d / "BH20" / "Calibration" / "999-calibration-properties.json").write_text("{not json")
    _edit(d / "BL14" / "Properties" / "BL14-heliostat-properties.json", _mut("kinematics_properties.actuators", [{}]))
    (d / "XX01" / "Calibration").mkdir(parents=True)
    shutil.copy(_first_bh20(d), d / "XX01" / "Calibration" / "5-calibration-properties.json")
    _edit(d / "calibration-timestamps.json", lambda t: t.update({"5": {"heliostat_id": "XX01", "datetime": "?"}}))
    f = load_paint_directory(d)
    r = f.report
    assert f.ids == ("BE36", "BF56", "BG23", "BH20")
    assert (r.heliostats_loaded, r.heliostats_skipped) == (4, 2)
    assert r.records_loaded == 392 - 9 and r.records_skipped == 1 + 9 + 1
    got = {(Path(e.file).relative_to(d).as_posix(), e.field) for e in r.skipped}
    assert got == {
        ("calibration-timestamps.json", "5.datetime"),
        ("BH20/Calibration/999-calibration-properties.json", None),
        ("BL14/Properties/BL14-heliostat-properties.json", "kinematics_properties.actuators"),
        ("BL14/Calibration", None),
        ("XX01/Properties/XX01-heliostat-properties.json", None),
    }
    for hid in ("BE36", "BF56", "BG23", "BH20"):
        assert _same(_valid(f, hid), _valid(emb_fleet, hid)), hid
    assert "XX01" in r.format()


# --------------------------------------------------------------------------------------
# records_to_fleet, the writer round trip
# --------------------------------------------------------------------------------------


def test_round_trip_bit_identical(tmp_path, raw_emb):
    tower, props, recs = raw_emb
    # Exercise every path: a record without time, one without UTIS, one without
    # HeliOS, weather with unknown entries, floats needing all 17 digits.
    recs = list(recs)
    recs[3] = dataclasses.replace(recs[3], datetime=None)
    recs[4] = dataclasses.replace(recs[4], focal_spot_utis=None)
    recs[5] = dataclasses.replace(recs[5], focal_spot_helios=None, sun_azimuth_deg=0.1 + 0.2)
    recs[6] = dataclasses.replace(recs[6], weather={**recs[6].weather, "temperature": 1 / 3})
    keep = {"BF56", "BL14", "BH20"}
    props = [p for p in props if p.heliostat_id in keep]
    recs = [r for r in recs if r.heliostat_id in keep]
    for centroid in ("utis", "helios"):
        expected = records_to_fleet(tower, props, recs, centroid=centroid)
        out = write_paint_directory(tmp_path / "sim", tower, props, recs)
        got = load_paint_directory(out, centroid=centroid)
        assert got.ids == expected.ids and got.target_names == expected.target_names
        assert _leaves_equal(got, expected)
        assert got.report.records_loaded == expected.report.records_loaded
    assert (tmp_path / "sim" / "calibration-with-weather.csv").exists()


def test_records_to_fleet_validates(raw_emb):
    tower, props, recs = raw_emb
    bl14 = [r for r in recs if r.heliostat_id == "BL14"]
    p = [x for x in props if x.heliostat_id == "BL14"]
    bad = dataclasses.replace(bl14[0], sun_elevation_deg=math.nan)
    stray = dataclasses.replace(bl14[1], heliostat_id="QQ01", record_id=1)
    f = records_to_fleet(tower, p, [bad, stray] + bl14[1:])
    assert f.report.records_loaded == 8 and f.report.records_skipped == 2 and f.report.heliostats_skipped == 1
    assert {e.field for e in f.report.skipped} == {"sun_elevation", "heliostat_id"}
    with pytest.raises(DataError):
        records_to_fleet(tower, p, [bad] + bl14[1:], strict=True)
    with pytest.raises(DataError):  # nothing loadable
        records_to_fleet(tower, [], bl14)


def test_heliostat_without_records(raw_emb):
    tower, props, recs = raw_emb
    f = records_to_fleet(tower, props[:2], [r for r in recs if r.heliostat_id == "BE36"])
    assert f.ids == ("BE36", "BF56")
    assert not np.asarray(f.mask[1]).any() and f.report.heliostats_loaded == 2
    assert any("no valid calibration record" in e.reason for e in f.report.flags)
    for leaf in (f.counts, f.focal_spot, f.context.sun):
        assert np.all(np.isfinite(np.asarray(leaf)))
    # Mid-range counts, sun south at 45 deg, spot at target 0's centre.
    a = props[1].actuators
    assert np.asarray(f.counts[1, 0]).tolist() == [round((x["min_increment"] + x["max_increment"]) / 2) for x in a]
    np.testing.assert_allclose(np.asarray(f.focal_spot[1, 0]), np.asarray(f.targets.centre[0]), atol=1e-12)


# --------------------------------------------------------------------------------------
# Padding, buckets, subsets, jit
# --------------------------------------------------------------------------------------


def test_bucket_size():
    assert [bucket_size(n) for n in (0, 1, 8, 9, 12, 13, 16, 17, 24, 25, 164, 193)] == [
        8,
        8,
        8,
        12,
        12,
        16,
        16,
        24,
        24,
        32,
        192,
        256,
    ]
    prev = 8
    for n in range(1, 5000):
        b = bucket_size(n)
        assert b >= n and b >= prev and (n <= 8 or b <= 1.5 * n)
        prev = b
    assert len({bucket_size(n) for n in range(1, 1025)}) == 15  # few shapes


def test_pad_fleet(emb_fleet):
    f = emb_fleet
    p = pad_fleet(f)
    assert (p.n_heliostats, p.n_records) == (8, 192) == (bucket_size(5), bucket_size(164))
    assert p.ids == EMB_IDS + ("", "", "")
    m = np.asarray(p.mask)
    assert not m[5:].any() and not m[:, 164:].any()
    assert np.all(np.asarray(p.record_id)[~m] == -1)
    for name in ("counts", "focal_spot"):
        a, b = np.asarray(getattr(f, name)), np.asarray(getattr(p, name))
        assert np.array_equal(b[:5, :164], a)
        assert np.all(np.isfinite(b))
    assert np.all(np.isfinite(np.asarray(p.context.sun)))
    assert _leaves_equal(jax.tree.map(lambda x: x[:5], p.geometry), f.geometry)
    assert _leaves_equal(jax.tree.map(lambda x: x[:5, :164], p.context), f.context)

    # A masked, vmapped reduction agrees between padded and unpadded fleets.
    def per_heliostat(fl):
        def one(sun, spot, mask, pos):
            d = spot - pos[None]
            cosang = jnp.sum(sun * d, -1) / jnp.linalg.norm(d, axis=-1)
            return jnp.sum(jnp.where(mask, cosang, 0.0)) / jnp.maximum(mask.sum(), 1).astype(cosang.dtype)

        return jax.jit(jax.vmap(one))(fl.context.sun, fl.focal_spot, fl.mask, fl.geometry.position)

    np.testing.assert_allclose(np.asarray(per_heliostat(p))[:5], np.asarray(per_heliostat(f)), rtol=1e-12)
    with pytest.raises(ValueError):
        pad_fleet(f, n_heliostats=3)
    q = pad_fleet(f, n_heliostats=5, n_records=170)
    assert (q.n_heliostats, q.n_records) == (5, 170) and q.ids == EMB_IDS
    # Padded slots of BL14 (9 records) copy its first record.
    h = f.index("BL14")
    assert np.array_equal(np.asarray(q.counts[h, 9:]), np.repeat(np.asarray(f.counts[h, :1]), 161, 0))


def test_subset_heliostat_and_jit(emb_fleet):
    f = emb_fleet
    s = fleet_subset(f, ["BL14", 0])
    assert s.ids == ("BL14", "BE36") and s.n_records == f.n_records
    assert np.array_equal(np.asarray(s.counts[0]), np.asarray(f.counts[4]))
    assert _leaves_equal(s.heliostat(1).geometry, f.heliostat("BE36").geometry)
    one = f.heliostat(2)
    assert one.id == "BG23" and one.counts.shape == (164, 2) and int(one.mask.sum()) == 52
    with pytest.raises(ValueError):
        f.index("nope")
    with pytest.raises(IndexError):
        f.heliostat(7)
    # A fleet is a pytree with hashable static fields: jit works and caches.
    total = jax.jit(lambda fl: jnp.sum(jnp.where(fl.mask[..., None], fl.counts, 0.0)))
    assert float(total(f)) == float(np.asarray(f.counts)[np.asarray(f.mask)].sum())
    hash(f.report)
    assert isinstance(f.report, LoadReport)


def test_degenerate_actuator_is_skipped(raw_emb):
    tower, props, recs = raw_emb
    bl14 = next(p for p in props if p.heliostat_id == "BL14")
    # each side within the bounds, but the stroke never closes the triangle: one angle
    # at both count limits (offset 1e300, which the law overflowed on, is out of bounds now)
    a0 = dict(bl14.actuators[0], offset=5.0, pivot_radius=0.02)
    bad = dataclasses.replace(bl14, actuators=(a0, bl14.actuators[1]))
    others = [p for p in props if p.heliostat_id in ("BH20",)]
    f = records_to_fleet(tower, [bad] + others, [r for r in recs if r.heliostat_id in ("BL14", "BH20")])
    assert f.ids == ("BH20",)
    fields = {e.field for e in f.report.skipped}
    assert fields == {"kinematics_properties.actuators[0]", "heliostat_id"}
    assert f.report.records_skipped == 9
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(f.geometry))


def test_numpy_scalars_from_a_simulator(tmp_path, raw_emb, unchecked):  # records annotated int get np.int64
    tower, props, recs = raw_emb
    p = next(p for p in props if p.heliostat_id == "BL14")
    rs = [
        dataclasses.replace(
            r,
            record_id=np.int64(r.record_id),
            axis_1_counts=np.int64(r.axis_1_counts),
            sun_azimuth_deg=np.float64(r.sun_azimuth_deg),
        )
        for r in recs
        if r.heliostat_id == "BL14"
    ]
    a = records_to_fleet(tower, [p], rs)
    b = load_paint_directory(write_paint_directory(tmp_path / "d", tower, [p], rs))
    assert a.report.records_loaded == 9 and _leaves_equal(a, b)


_any_value = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**20), 10**20),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6),
    st.lists(st.floats(allow_nan=True), max_size=4),
    st.tuples(st.floats(-100, 100), st.floats(-200, 400), st.floats(-1e6, 1e6)),
)
_RECORD_FIELDS = (
    "record_id",
    "heliostat_id",
    "axis_1_counts",
    "axis_2_counts",
    "target_name",
    "sun_azimuth_deg",
    "sun_elevation_deg",
    "focal_spot_helios",
    "focal_spot_utis",
    "datetime",
    "weather",
)


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],  # `unchecked` is stateless
)
@given(field=st.sampled_from(_RECORD_FIELDS), value=_any_value)
def test_hypothesis_records_to_fleet(raw_emb, unchecked, field, value):
    """A record with a random value in any field is loaded or skipped and reported;
    nothing but DataError escapes and the other records are untouched."""
    tower, props, recs = raw_emb
    p = [x for x in props if x.heliostat_id == "BL14"]
    rs = [r for r in recs if r.heliostat_id == "BL14"]
    bad = dataclasses.replace(rs[0], **{field: value})
    f = records_to_fleet(tower, p, [bad] + rs[1:])
    r = f.report
    assert r.records_loaded + r.records_skipped == 9
    loaded = set(np.asarray(f.record_id)[np.asarray(f.mask)].tolist())
    assert {x.record_id for x in rs[1:]} <= loaded


def test_record_with_a_non_string_heliostat_id_is_skipped_not_crashing(raw_emb, unchecked):
    """Regression (found by Hypothesis): an unhashable heliostat_id used to raise TypeError."""
    tower, props, recs = raw_emb
    p = next(p for p in props if p.heliostat_id == "BL14")
    rs = [r for r in recs if r.heliostat_id == "BL14"]
    bad = dataclasses.replace(rs[0], heliostat_id=[])
    f = records_to_fleet(tower, [p], [bad] + rs[1:])
    assert f.report.records_loaded == len(rs) - 1
    assert f.report.skipped[-1].field == "heliostat_id"
    with pytest.raises(DataError, match="heliostat_id"):
        records_to_fleet(tower, [p], [bad] + rs[1:], strict=True)


def test_unreadable_folders_are_named_not_silently_empty(tmp_path, monkeypatch):
    """A heliostat folder or a Calibration folder the process may not read (a listing
    that fails looks like an empty or missing folder) is named in the load report; the
    other heliostats load as before. Permissions are simulated: the tests may run as root."""
    import os
    import shutil

    data = tmp_path / "paint"
    shutil.copytree(default_data_dir(), data)
    locked_heliostat, locked_calibration = data / "BG23", data / "BF56" / "Calibration"
    real_access, real_scandir = os.access, os.scandir
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: Path(p) != locked_heliostat and real_access(p, mode, **kw))

    def scandir(path=".", *args, **kwargs):
        if Path(path) == locked_calibration:
            raise PermissionError(13, "Permission denied", str(path))
        return real_scandir(path, *args, **kwargs)

    monkeypatch.setattr(os, "scandir", scandir)
    fleet = load_paint_directory(data)
    assert set(fleet.ids) == {"BE36", "BF56", "BH20", "BL14"}
    named = {Path(e.file).relative_to(data).as_posix(): e.reason for e in fleet.report.skipped}
    assert "permission denied" in named["BG23"].lower() and "Permission denied" in named["BF56/Calibration"]
    assert not np.asarray(fleet.mask)[list(fleet.ids).index("BF56")].any()
    assert np.asarray(fleet.mask)[list(fleet.ids).index("BE36")].sum() == 164


def test_fleet_from_integer_counts_keeps_focal_spots_and_origin_in_float64(emb_fleet):
    """Motor counts are integers: they used to set the dtype of the focal spots (rounded
    to whole metres) and of the site origin ([50, 6, 87])."""
    fl = emb_fleet
    kw = {"ids": fl.ids, "origin_lla": tuple(np.asarray(fl.origin_lla))}
    counts = np.asarray(fl.counts)
    made = hj.fleet_from_arrays(fl.geometry, counts.astype(np.int64), fl.context, fl.focal_spot, fl.mask, **kw)
    assert made.counts.dtype == made.focal_spot.dtype == made.origin_lla.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(made.focal_spot), np.asarray(fl.focal_spot))
    np.testing.assert_array_equal(np.asarray(made.origin_lla), np.asarray(fl.origin_lla))
    f32 = hj.fleet_from_arrays(fl.geometry, counts.astype(np.float32), fl.context, fl.focal_spot, fl.mask, **kw)
    assert f32.origin_lla.dtype == jnp.float64


def test_fleet_from_arrays_names_a_mask_that_is_not_boolean(emb_fleet, unchecked):
    fl = emb_fleet
    with pytest.raises(ValueError, match="mask: expected booleans"):
        hj.fleet_from_arrays(fl.geometry, fl.counts, fl.context, fl.focal_spot, np.where(fl.mask, 1.0, np.nan))
    for origin in ((np.nan, 6.4, 87.0), (95.0, 6.4, 87.0), (50.9, 6.4)):
        with pytest.raises(ValueError, match="origin_lla: expected a WGS84"):
            hj.fleet_from_arrays(fl.geometry, fl.counts, fl.context, fl.focal_spot, origin_lla=origin)
