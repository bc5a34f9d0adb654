"""Tests of heliojax._paint: raw PAINT readers, validation and writers.

Reference values are read by hand from the shared files (numbers quoted below) or
counted here independently with the json/csv modules.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import json
import math
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from heliojax._errors import DataError
from heliojax.paint import (
    CSV_COLUMNS,
    WEATHER_KEYS,
    CalibrationRecord,
    TimestampEntry,
    default_data_dir,
    read_calibration_record,
    read_heliostat_properties,
    read_timestamps,
    read_tower,
    read_weather_csv,
    validate_record,
    write_calibration_record,
    write_heliostat_properties,
    write_timestamps,
    write_tower,
    write_weather_csv,
)

EMB = default_data_dir()
TOWER = EMB / "WRI1030197-tower-measurements.json"
BE36_PROPS = EMB / "BE36" / "Properties" / "BE36-heliostat-properties.json"
BE36_REC = EMB / "BE36" / "Calibration" / "118671-calibration-properties.json"


@pytest.fixture(scope="module")
def tower():
    return read_tower(TOWER)


@pytest.fixture(scope="module")
def be36():
    return read_heliostat_properties(BE36_PROPS)


# --------------------------------------------------------------------------------------
# Reading real files
# --------------------------------------------------------------------------------------


def test_read_tower(tower):
    assert tower.plant_id == "WRI1030197"
    assert tower.origin_lla == (50.913421122592574, 6.387824755874856, 87.0)
    assert tower.planar_target_names == (
        "solar_tower_juelich_upper",
        "solar_tower_juelich_lower",
        "multi_focus_tower",
    )
    rec = tower.targets["receiver"]  # kept, but not a calibration target
    assert rec.type == "convex_cylinder" and not rec.is_planar_target
    assert rec.extra == {"radius": 4.14, "opening_angle": 60}
    assert rec.normal == (0.0, 0.90630779, -0.42261826)
    upper = tower.targets["solar_tower_juelich_upper"]
    assert upper.points["upper_left"] == (50.91339196507306, 6.387885982262168, 133.684)
    assert upper.normal == (0.0, 1.0, 0.0)


def test_read_heliostat_properties(be36):
    p = be36
    assert p.heliostat_id == "BE36"
    assert p.position_lla == (50.915305291964, 6.387837863755278, 88.69644928)
    assert (p.width, p.height) == (3.2200000286102295, 2.559999942779541)
    a1, a2 = p.actuators
    assert a1["increment"] == 154166.6667 and a1["max_increment"] == 69001
    assert a1["initial_stroke_length"] == 0.075676335 and a1["clockwise_axis_movement"] == 0
    assert a2["offset"] == 0.340771 and a2["pivot_radius"] == 0.3191 and a2["clockwise_axis_movement"] == 1
    assert a2["initial_angle"] == 0.937086489 and a2["max_increment"] == 75454
    assert isinstance(a1["max_increment"], int) and a1["type_axis"] == "linear"
    assert p.concentrator_translation == (0.0, 0.175, 0.0)
    assert p.joint_translation_1 == (0.0, 0.0, 0.0) == p.joint_translation_2
    assert len(p.facets) == 4 and p.facets[1].translation_vector == (0.8075, 0.6425, 0.0402)
    assert p.canting_type == "receiver canting" and p.renovation == "2022-06-09"


def test_read_calibration_record(tower, be36):
    ts = read_timestamps(EMB / "calibration-timestamps.json")
    r = read_calibration_record(BE36_REC, timestamps=ts, tower=tower, properties=be36)
    assert r.record_id == 118671 and r.heliostat_id == "BE36"
    assert (r.axis_1_counts, r.axis_2_counts) == (45501, 53811)
    assert r.target_name == "solar_tower_juelich_lower"
    assert r.sun_elevation_deg == 54.66615202629741 and r.sun_azimuth_deg == -48.91974860208279
    assert r.focal_spot_helios == (50.91339203951505, 6.387820495303746, 123.0394382264574)
    assert r.focal_spot_utis == (50.9133920558005, 6.387820891167903, 122.98824310302734)
    assert r.datetime == "2022-06-12T13:27:37Z"
    assert set(r.weather) == set(WEATHER_KEYS) and all(math.isnan(v) for v in r.weather.values())


def test_timestamps_and_csv_of_embedded_data():
    ts = read_timestamps(EMB / "calibration-timestamps.json")
    files = list(EMB.glob("*/Calibration/*-calibration-properties.json"))
    assert len(ts) == len(files) == 392
    assert ts[118671] == TimestampEntry("BE36", "2022-06-12T13:27:37Z")
    rows = read_weather_csv(EMB / "calibration-with-weather.csv")
    assert {r.heliostat_id for r in rows} == {"BE36", "BF56"} and len(rows) == 100
    # The CSV's focal spot is the HeliOS centroid of the same record (module docstring).
    for r in rows[:10]:
        j = read_calibration_record(EMB / r.heliostat_id / "Calibration" / f"{r.record_id}-calibration-properties.json")
        assert r.focal_spot_helios == j.focal_spot_helios
        assert (r.axis_1_counts, r.sun_azimuth_deg) == (j.axis_1_counts, j.sun_azimuth_deg)
        assert r.datetime == ts[r.record_id].datetime


def test_every_shared_file_reads(shared_paint):
    tower = read_tower(shared_paint / "WRI1030197-tower-measurements.json")
    ts = read_timestamps(shared_paint / "calibration-timestamps.json")
    assert len(ts) == 1706
    props = {}
    for f in sorted(shared_paint.glob("*/Properties/*-heliostat-properties.json")):
        p = read_heliostat_properties(f)
        props[p.heliostat_id] = p
    assert len(props) == 27 and "BG63" not in props
    n = no_time = helios_only = 0
    for f in sorted(shared_paint.glob("*/Calibration/*-calibration-properties.json")):
        hid = f.parents[1].name
        r = read_calibration_record(f, timestamps=ts, tower=tower, properties=props.get(hid))
        n += 1
        no_time += r.datetime is None
        helios_only += r.focal_spot_utis is None
        assert r.focal_spot_helios is not None
    # Counted independently: files absent from the timestamps, files without "UTIS".
    ids = {int(f.name.split("-")[0]) for f in shared_paint.glob("*/Calibration/*.json")}
    no_utis = sum(
        "UTIS" not in json.loads(f.read_text()).get("focal_spot", {}) for f in shared_paint.glob("*/Calibration/*.json")
    )
    assert n == 1712
    assert no_time == len(ids - set(ts)) == 6
    assert helios_only == no_utis == 10
    rows = read_weather_csv(shared_paint / "calibration-with-weather.csv")
    assert len(rows) == 6057 and len({r.heliostat_id for r in rows}) == 129


# --------------------------------------------------------------------------------------
# Bad input: each kind raises DataError naming file and field
# --------------------------------------------------------------------------------------


def _set(d, dotted, value):
    keys = dotted.split(".")
    for k in keys[:-1]:
        d = d[int(k)] if isinstance(d, list) else d[k]
    last = keys[-1]
    if value is _DELETE:
        del d[last]
    elif isinstance(d, list):
        d[int(last)] = value
    else:
        d[last] = value


_DELETE = object()

RECORD_CASES = [
    # (dotted path to change, new value, expected DataError.field, words in the reason)
    ("motor_position.axis_1_motor_position", _DELETE, "motor_position.axis_1_motor_position", "missing"),
    ("motor_position.axis_1_motor_position", "45501", "motor_position.axis_1_motor_position", "number"),
    ("motor_position.axis_2_motor_position", True, "motor_position.axis_2_motor_position", "number"),
    ("motor_position.axis_1_motor_position", 45501.5, "motor_position.axis_1_motor_position", "integer"),
    ("motor_position.axis_1_motor_position", 10**400, "motor_position.axis_1_motor_position", "range"),
    ("motor_position.axis_2_motor_position", 75455, "motor_position.axis_2_motor_position", "outside"),
    ("motor_position.axis_1_motor_position", -1, "motor_position.axis_1_motor_position", "outside"),
    ("motor_position", [1, 2], "motor_position", "object"),
    ("sun_elevation", float("nan"), "sun_elevation", "finite"),
    ("sun_azimuth", float("inf"), "sun_azimuth", "finite"),
    ("sun_azimuth", None, "sun_azimuth", "number"),
    ("sun_elevation", 91.0, "sun_elevation", "outside"),
    ("target_name", "no_such_target", "target_name", "unknown target"),
    ("target_name", "receiver", "target_name", "not a planar"),
    ("target_name", 3, "target_name", "string"),
    ("focal_spot.UTIS", [50.9, 6.38], "focal_spot.UTIS", "3 numbers"),
    ("focal_spot.HeliOS.1", "x", "focal_spot.HeliOS[1]", "number"),
    ("focal_spot.HeliOS.2", float("-inf"), "focal_spot.HeliOS[2]", "finite"),
    ("focal_spot", {}, "focal_spot", "neither"),
    ("focal_spot", {"HeliOS": None, "UTIS": None}, "focal_spot", "neither"),
]


@pytest.mark.parametrize("path,value,field,words", RECORD_CASES)
def test_bad_calibration_record(tmp_path, tower, be36, path, value, field, words):
    data = json.loads(BE36_REC.read_text())
    _set(data, path, value)
    f = tmp_path / "BE36" / "Calibration" / "118671-calibration-properties.json"
    f.parent.mkdir(parents=True)
    f.write_text(json.dumps(data))  # NaN/Infinity tokens allowed by json.dumps
    with pytest.raises(DataError) as e:
        read_calibration_record(f, tower=tower, properties={"BE36": be36})
    assert e.value.file == str(f) and e.value.field == field
    assert words in e.value.reason
    assert str(f) in str(e.value) and field in str(e.value)


@pytest.mark.parametrize(
    "content,words",
    [
        (b"{", "malformed JSON"),
        (b"\xff\xfe\x00junk", "UTF-8"),
        (b"[1, 2]", "object"),
        (b"", "malformed JSON"),
        (b"[" * 100_000, "malformed JSON"),
    ],
)
def test_malformed_calibration_file(tmp_path, content, words):
    f = tmp_path / "BE36" / "Calibration" / "1-calibration-properties.json"
    f.parent.mkdir(parents=True)
    f.write_bytes(content)
    with pytest.raises(DataError) as e:
        read_calibration_record(f)
    assert e.value.file == str(f) and e.value.field is None and words in e.value.reason


def test_record_context_errors(tmp_path, tower, be36):
    f = tmp_path / "BG63" / "Calibration" / "118671-calibration-properties.json"
    f.parent.mkdir(parents=True)
    f.write_bytes(BE36_REC.read_bytes())
    with pytest.raises(DataError) as e:  # heliostat without a properties file
        read_calibration_record(f, tower=tower, properties={"BE36": be36})
    assert e.value.field == "heliostat_id" and "no properties" in e.value.reason
    ts = {118671: TimestampEntry("BE36", "2022-06-12T13:27:37Z")}
    with pytest.raises(DataError) as e:  # timestamps assign the record to another heliostat
        read_calibration_record(f, timestamps=ts)
    assert e.value.field == "heliostat_id" and "BE36" in e.value.reason
    bad_name = tmp_path / "BE36" / "Calibration" / "abc-calibration-properties.json"
    bad_name.parent.mkdir(parents=True)
    bad_name.write_bytes(BE36_REC.read_bytes())
    with pytest.raises(DataError) as e:
        read_calibration_record(bad_name)
    assert e.value.file == str(bad_name) and e.value.field is None
    with pytest.raises(DataError) as e:
        read_calibration_record(tmp_path / "nothing" / "5-calibration-properties.json", heliostat_id="X")
    assert "cannot read" in e.value.reason


A0 = "kinematics_properties.actuators.0"
A1 = "kinematics_properties.actuators.1"
PROPERTY_CASES = [
    ("heliostat_position", _DELETE, "heliostat_position", "missing"),
    ("heliostat_position.0", 95.0, "heliostat_position", "latitude"),
    ("heliostat_position", "50.9, 6.3, 88", "heliostat_position", "3 numbers"),
    ("width", -1.0, "width", "positive"),
    ("height", float("nan"), "height", "finite"),
    ("initial_orientation", [1.0, 0.0, 0.0], "initial_orientation", "south"),
    ("kinematics_properties.actuators", [{}], "kinematics_properties.actuators", "2 actuators"),
    (f"{A0}.increment", "abc", "kinematics_properties.actuators[0].increment", "number"),
    (f"{A0}.increment", 0, "kinematics_properties.actuators[0].increment", "positive"),
    (f"{A1}.initial_stroke_length", float("nan"), "kinematics_properties.actuators[1].initial_stroke_length", "finite"),
    (f"{A1}.offset", _DELETE, "kinematics_properties.actuators[1].offset", "missing"),
    (f"{A0}.type_axis", "hydraulic", "kinematics_properties.actuators[0].type_axis", "linear, ideal"),
    (f"{A1}.clockwise_axis_movement", 2, "kinematics_properties.actuators[1].clockwise_axis_movement", "0 or 1"),
    (f"{A0}.max_increment", -5, "kinematics_properties.actuators[0].max_increment", "min_increment"),
    (f"{A0}.min_increment", 0.5, "kinematics_properties.actuators[0].min_increment", "integer"),
    ("kinematics_properties.joint_translation_e_1", _DELETE, "kinematics_properties.joint_translation_e_1", "missing"),
    (
        "kinematics_properties.concentrator_translation_n",
        float("inf"),
        "kinematics_properties.concentrator_translation_n",
        "finite",
    ),
    ("facet_properties.facets.2.canting_n", _DELETE, "facet_properties.facets[2].canting_n", "missing"),
    ("facet_properties.number_of_facets", 5, "facet_properties.number_of_facets", "4 facets"),
    ("renovation", 2022, "renovation", "string"),
]


@pytest.mark.parametrize("path,value,field,words", PROPERTY_CASES)
def test_bad_heliostat_properties(tmp_path, path, value, field, words):
    data = json.loads(BE36_PROPS.read_text())
    _set(data, path, value)
    f = tmp_path / "BE36-heliostat-properties.json"
    f.write_text(json.dumps(data))
    with pytest.raises(DataError) as e:
        read_heliostat_properties(f)
    assert e.value.file == str(f) and e.value.field == field
    assert words in e.value.reason


def test_bad_tower(tmp_path):
    base = json.loads(TOWER.read_text())
    cases = [
        ("power_plant_properties.coordinates", _DELETE, "power_plant_properties.coordinates"),
        (
            "solar_tower_juelich_upper.coordinates.lower_left",
            _DELETE,
            "solar_tower_juelich_upper.coordinates.lower_left",
        ),
        ("multi_focus_tower.normal_vector", [0, 0, 0], "multi_focus_tower.normal_vector"),
        ("receiver.coordinates.center.1", "x", "receiver.coordinates.center[1]"),
        ("receiver.type", None, "receiver.type"),
    ]
    for path, value, field in cases:
        data = copy.deepcopy(base)
        _set(data, path, value)
        f = tmp_path / "X-tower-measurements.json"
        f.write_text(json.dumps(data))
        with pytest.raises(DataError) as e:
            read_tower(f)
        assert (e.value.file, e.value.field) == (str(f), field), path


def test_bad_timestamps(tmp_path):
    f = tmp_path / "calibration-timestamps.json"
    f.write_text(
        json.dumps(
            {
                "1": {"heliostat_id": "AA", "datetime": "2022-06-10T12:15:59Z"},
                "2": {"heliostat_id": "AA", "datetime": "yesterday"},
                "x3": {"heliostat_id": "AA", "datetime": "2022-06-10T12:15:59Z"},
                "4": {"heliostat_id": 7, "datetime": "2022-06-10T12:15:59Z"},
            }
        )
    )
    with pytest.raises(DataError) as e:
        read_timestamps(f)
    assert (e.value.file, e.value.field) == (str(f), "2.datetime")
    errors = []
    ts = read_timestamps(f, on_error=errors.append)
    assert list(ts) == [1]
    assert [x.field for x in errors] == ["2.datetime", "x3", "4.heliostat_id"]


def test_a_record_listed_twice_in_the_timestamps_is_named(tmp_path):
    """JSON keeps the last of two equal keys without a word; a record id given twice with
    different entries (also as "7" and "07") is named and neither entry is used; an exact
    repeat is harmless."""
    f = tmp_path / "calibration-timestamps.json"
    entry = '{"heliostat_id": "AA", "datetime": "2022-06-10T12:15:59Z"}'
    other = '{"heliostat_id": "AB", "datetime": "2022-06-10T12:15:59Z"}'
    f.write_text(f'{{"1": {entry}, "2": {entry}, "1": {other}}}')
    with pytest.raises(DataError) as e:
        read_timestamps(f)
    assert (e.value.file, e.value.field) == (str(f), "1") and "twice" in e.value.reason
    errors = []
    assert sorted(read_timestamps(f, on_error=errors.append)) == [2]  # the other entries are kept
    assert [(x.field, "twice" in x.reason) for x in errors] == [("1", True)]
    f.write_text(f'{{"1": {entry}, "2": {entry}, "1": {entry}, "7": {entry}, "07": {other}, "3": {entry}}}')
    errors = []
    assert sorted(read_timestamps(f, on_error=errors.append)) == [1, 2, 3]
    assert [(x.field, "twice" in x.reason) for x in errors] == [("07", True)]


def test_bad_weather_csv(tmp_path):
    src = (EMB / "calibration-with-weather.csv").read_text().splitlines()
    cells = src[2].split(",")
    cells[CSV_COLUMNS.index("sun_azimuth")] = "east"
    lines = [src[0], src[1], ",".join(cells), src[3], "a,b"]
    f = tmp_path / "w.csv"
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError) as e:
        read_weather_csv(f)
    assert (e.value.file, e.value.field) == (str(f), "row 3.sun_azimuth")
    errors = []
    rows = read_weather_csv(f, on_error=errors.append)
    assert len(rows) == 2 and [x.field for x in errors] == ["row 3.sun_azimuth", "row 5"]
    g = tmp_path / "no_col.csv"
    g.write_text("heliostat_id,timestamp\nAA,\n")
    with pytest.raises(DataError) as e:
        read_weather_csv(g)
    assert e.value.field == "sample_id" and "missing column" in e.value.reason


# --------------------------------------------------------------------------------------
# Property-based: malformed input never raises anything but DataError
# --------------------------------------------------------------------------------------

json_scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8)
)
json_values = st.recursive(
    json_scalars,
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=12,
)
_RECORD_TEMPLATE = json.loads(BE36_REC.read_text())
_PROPS_TEMPLATE = json.loads(BE36_PROPS.read_text())


def _paths(d, prefix=()):
    """All key paths of a nested JSON value."""
    out = [prefix] if prefix else []
    if isinstance(d, dict):
        for k, v in d.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            out += _paths(v, prefix + (i,))
    return out


def _mutated(template, data):
    doc = copy.deepcopy(template)
    for _ in range(data.draw(st.integers(1, 3))):
        paths = _paths(doc)
        if not paths:
            break
        path = data.draw(st.sampled_from(paths))
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        if data.draw(st.booleans()) and isinstance(parent, dict):
            del parent[path[-1]]
        else:
            parent[path[-1]] = data.draw(json_values)
    return doc


def _only_data_errors(content: bytes, reader, name: str):
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "BE36" / ("Calibration" if "calibration" in name else "Properties") / name
        f.parent.mkdir(parents=True)
        f.write_bytes(content)
        try:
            reader(f)
        except DataError as e:
            assert e.file == str(f)
            return "error"
        return "ok"


_RECORD_CONTEXT: dict = {}


def _read_record(f, _ctx=_RECORD_CONTEXT):
    if not _ctx:
        _ctx["tower"] = read_tower(TOWER)
        _ctx["props"] = {"BE36": read_heliostat_properties(BE36_PROPS)}
    return read_calibration_record(f, tower=_ctx["tower"], properties=_ctx["props"])


_SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@_SETTINGS
@given(st.data())
def test_hypothesis_mutated_calibration(data):
    doc = _mutated(_RECORD_TEMPLATE, data)
    _only_data_errors(json.dumps(doc).encode(), _read_record, "118671-calibration-properties.json")


@_SETTINGS
@given(json_values)
def test_hypothesis_random_calibration(value):
    out = _only_data_errors(json.dumps(value).encode(), _read_record, "1-calibration-properties.json")
    assert out == "error"  # a random value is never a valid record


@_SETTINGS
@given(st.data())
def test_hypothesis_mutated_properties(data):
    doc = _mutated(_PROPS_TEMPLATE, data)
    _only_data_errors(json.dumps(doc).encode(), read_heliostat_properties, "BE36-heliostat-properties.json")


@_SETTINGS
@given(st.binary(max_size=200) | st.text(max_size=100).map(str.encode))
def test_hypothesis_junk_bytes(content):
    for reader, name in (
        (_read_record, "1-calibration-properties.json"),
        (read_heliostat_properties, "BE36-heliostat-properties.json"),
    ):
        _only_data_errors(content, reader, name)


# --------------------------------------------------------------------------------------
# Writers
# --------------------------------------------------------------------------------------


def test_writers_round_trip_real_files(tmp_path, tower, be36):
    write_tower(tmp_path / "t.json", tower)
    assert json.loads((tmp_path / "t.json").read_text()) == json.loads(TOWER.read_text())
    assert dataclasses.replace(read_tower(tmp_path / "t.json"), source=tower.source) == tower
    write_heliostat_properties(tmp_path / "BE36-heliostat-properties.json", be36)
    assert json.loads((tmp_path / "BE36-heliostat-properties.json").read_text()) == json.loads(BE36_PROPS.read_text())
    r = read_calibration_record(BE36_REC)
    out = tmp_path / "BE36" / "Calibration" / "118671-calibration-properties.json"
    write_calibration_record(out, r)
    assert json.loads(out.read_text()) == json.loads(BE36_REC.read_text())
    assert dataclasses.replace(read_calibration_record(out), source=r.source) == r
    src = EMB / "calibration-timestamps.json"
    ts = read_timestamps(src)
    write_timestamps(tmp_path / "ts.json", ts)
    assert (tmp_path / "ts.json").read_text().rstrip() == src.read_text().rstrip()  # same format too
    assert not list(tmp_path.glob(".*heliojax-tmp*"))  # atomic writes leave no temporaries


def test_weather_csv_round_trip(tmp_path, tower):
    rows = read_weather_csv(EMB / "calibration-with-weather.csv")
    odd = dataclasses.replace(
        rows[0], datetime=None, weather={**rows[0].weather, "dni": math.nan}, sun_azimuth_deg=0.1 + 0.2
    )  # a float whose repr needs 17 digits
    rows = (odd,) + rows[1:]
    f = tmp_path / "w.csv"
    write_weather_csv(f, rows, tower=tower)
    back = read_weather_csv(f)
    assert len(back) == len(rows)
    for a, b in zip(rows, back):
        assert dataclasses.replace(b, source=a.source) == a
    with open(f, newline="") as fh:
        assert tuple(next(csv.reader(fh))) == CSV_COLUMNS


def test_validate_record(unchecked):
    r = CalibrationRecord(
        record_id=5,
        heliostat_id="AA01",
        axis_1_counts=1,
        axis_2_counts=2,
        target_name="t",
        sun_azimuth_deg=10.0,
        sun_elevation_deg=20.0,
        focal_spot_helios=(50.0, 6.0, 100.0),
    )
    assert validate_record(r) == r
    for bad, field in [
        (dataclasses.replace(r, sun_elevation_deg=math.nan), "sun_elevation"),
        (dataclasses.replace(r, focal_spot_helios=None), "focal_spot"),
        (dataclasses.replace(r, datetime="noon"), "datetime"),
        (dataclasses.replace(r, weather={"temperature": math.inf}), "weather.temperature"),
        (dataclasses.replace(r, weather={"rain": 1.0}), "weather.rain"),
        (dataclasses.replace(r, record_id=-1), "record_id"),
        (dataclasses.replace(r, axis_1_counts=1.5), "motor_position.axis_1_motor_position"),
    ]:
        with pytest.raises(DataError) as e:
            validate_record(bad)
        assert e.value.field == field and e.value.file == "<memory>"


def test_a_folder_holding_none_of_the_requested_heliostats_is_one_line():
    """Another fleet's folder (``plan --paint-dir`` given the wrong download): one line
    naming the requested heliostats and the folder's own, not a load report of every
    requested heliostat (was 16 lines)."""
    from heliojax.paint import load_paint_directory

    with pytest.raises(DataError) as err:
        load_paint_directory(EMB, heliostats=["ZZ01", "ZZ02"])
    text = str(err.value)
    assert "holds none of the requested heliostats (ZZ01, ZZ02)" in text
    assert "its heliostats: BE36, BF56" in text and "\n" not in text


def test_close_pairs_by_numpy_and_by_tree_agree(monkeypatch):
    """The overlap check's neighbour search: all distances at once for a few hundred
    heliostats, a k-d tree for large fields; the same sorted pairs, checked by hand
    for one planted pair and for the reach being inclusive."""
    import numpy as np

    from heliojax.paint import _flags

    rng = np.random.default_rng(0)
    xy = rng.uniform(0.0, 300.0, (700, 2))
    xy[5] = xy[4] + [0.5, 0.0]
    xy[7] = xy[6] + [6.0, 0.0]  # exactly at the reach
    by_numpy = _flags.close_pairs(xy, 6.0)
    monkeypatch.setattr(_flags, "CLOSE_PAIRS_BY_TREE", 2)
    assert _flags.close_pairs(xy, 6.0) == by_numpy
    assert (4, 5) in by_numpy and (6, 7) in by_numpy and len(by_numpy) > 10
    assert all(i < j and np.linalg.norm(xy[i] - xy[j]) <= 6.0 for i, j in by_numpy)
