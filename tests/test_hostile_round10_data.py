"""Hostile-input round 10 (data and library): every field of
:class:`heliojax.neural.NeuralConfig` is checked (a NaN ``fallback_tolerance`` switched
the safeguard off); ``accept`` with nothing measured reported ``level2.pass: true`` and
the contract's efficiency as "measured"; ``fetch`` named broken STAC fields with
Python's exception text; a properties file listing its facets 25 times traced 25 times
the power."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from helpers import run_cli
from test_acceptance_io import CONTRACT
from test_stac import build_catalogue, item_json

import heliojax as hj
from heliojax._errors import DataError
from heliojax.acceptance import JUELICH_COORDINATES, FieldData, juelich_receiver, run_acceptance, typical_year
from heliojax.acceptance._io import Contract, ParameterSpec
from heliojax.neural import NeuralConfig
from heliojax.paint import fetch_catalog, read_facets, read_heliostat_properties

# --------------------------------------------------------------------------- F8 NeuralConfig

BAD_NUMBERS = [
    ("fallback_tolerance", math.nan),
    ("fallback_tolerance", math.inf),
    ("fallback_tolerance", -0.1),
    ("residual_lr", math.nan),
    ("residual_lr", -1e-3),
    ("finetune_lr", 0.0),
    ("pretrain_lr", math.inf),
    ("huber_delta", -1.0),
    ("residual_huber_mrad", math.nan),
    ("plateau_factor", 0.0),
    ("plateau_factor", 1.5),
    ("plateau_rtol", math.nan),
    ("sun_jitter_deg", -2.0),
    ("spot_jitter_m", math.nan),
    ("synthetic_val_fraction", math.nan),
    ("val_fraction", math.nan),
    ("min_val", -3),
    ("plateau_patience", 0),
    ("batch_size", 0),
    ("n_synthetic", 1),  # all of it validation, nothing to pretrain on
    ("hidden", (6, 0, 4)),
]


@pytest.mark.parametrize(("field", "value"), BAD_NUMBERS, ids=lambda v: repr(v))
def test_neural_config_refuses_each_out_of_range_field_by_name(field, value):
    with pytest.raises(ValueError, match=field.split("[")[0]):
        NeuralConfig(**{field: value})


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("dtype", "float7"),
        ("dtype", "int32"),
        ("dtype", None),
        ("n_synthetic", 2.5),
        ("min_val", True),
        ("hidden", "6"),
    ],
    ids=lambda v: repr(v),
)
def test_neural_config_refuses_ill_typed_fields_by_name(unchecked, field, value):
    with pytest.raises(TypeError, match=field):
        NeuralConfig(**{field: value})


def test_neural_config_keeps_good_values_and_normalises_them(unchecked):
    c = NeuralConfig(min_val=0, hidden=(np.int64(4),), dtype="f8", n_synthetic=np.int64(20), fallback_tolerance=0)
    assert c.hidden == (4,) and c.dtype == "float64" and type(c.n_synthetic) is int and c.fallback_tolerance == 0.0
    assert NeuralConfig() == NeuralConfig()  # hashable, equal: a static argument of the compiled programs
    hash(NeuralConfig())


# --------------------------------------------------------------------------- F3 accept with nothing measured


@pytest.fixture(scope="module")
def coarse_sun():
    return typical_year(*JUELICH_COORDINATES, step_minutes=360)


@pytest.mark.parametrize("n_measured", [0, 1])
def test_level2_is_not_assessed_without_two_measurements(coarse_sun, n_measured):
    n = 6
    positions = np.stack([np.linspace(-30, 30, n), np.full(n, 80.0), np.zeros(n)], axis=1)
    tracking = np.full(n, np.nan)
    tracking[:n_measured] = 1.9
    field = FieldData(ids=tuple(f"H{i}" for i in range(n)), positions=positions, values={"tracking_mrad": tracking})
    contract = Contract(parameters={"tracking_mrad": ParameterSpec(2.0, 0.2, 0.04)})
    res = run_acceptance(field, contract, juelich_receiver(), JUELICH_COORDINATES, sun=coarse_sun)
    l2 = res.report["level2"]
    assert l2["pass"] is None and l2["assessed"] is False, l2
    assert l2["annual_efficiency_measured"] is None and l2["relative_difference"] is None
    assert l2["parameters_measured"] == [] and l2["parameters_from_contract"] == ["tracking_mrad"]
    assert l2["annual_efficiency_contract"] > 0 and all(m["efficiency_measured"] is None for m in l2["monthly"])
    assert res.yield_measured is None and res.report["verdict"] == "inconclusive"
    why = "not measured" if n_measured == 0 else "1 measured, at least 2 needed"
    assert f"tracking_mrad: {why}" in res.report["reasons"], res.report["reasons"]
    assert any(r.startswith("level 2: not assessed") for r in res.report["reasons"])
    json.dumps(res.report)


def _accept(tmp_path, capsys, csv_text: str) -> tuple[dict, str]:
    """``heliojax accept`` of a field CSV under :data:`CONTRACT`: the report's level 2
    and the printed output."""
    field = tmp_path / "f.csv"
    field.write_text(csv_text)
    contract = tmp_path / "c.toml"
    contract.write_text(CONTRACT)
    report = tmp_path / "acc.json"
    rc, out, err = run_cli(
        ["accept", "--results", str(field), "--contract", str(contract), "--report", str(report)], capsys
    )
    assert rc == 0, err
    return json.loads(report.read_text())["level2"], out


def test_accept_cli_with_empty_cells_does_not_print_a_measured_efficiency(tmp_path, capsys):
    l2, out = _accept(tmp_path, capsys, "heliostat_id,east_m,north_m,tracking_mrad\nA,0,50,\nB,12,50,\nC,-12,62,\n")
    assert l2["pass"] is None and l2["annual_efficiency_measured"] is None
    line = next(x for x in out.splitlines() if x.startswith("annual efficiency"))
    assert "measured: not assessed" in line and "contract's" in line, line


def test_a_partly_measured_field_names_the_contract_values_it_assumes(tmp_path, capsys):
    rows = [f"H{i},{6 * i - 30},{60 + i},{1.8 + 0.05 * i}," for i in range(10)]
    l2, out = _accept(
        tmp_path, capsys, "heliostat_id,east_m,north_m,tracking_mrad,slope_mrad\n" + "\n".join(rows) + "\n"
    )
    assert l2["assessed"] and l2["parameters_measured"] == ["tracking_mrad"]
    assert l2["parameters_from_contract"] == ["slope_mrad"] and isinstance(l2["pass"], bool)
    assert "contract's values assumed for slope_mrad" in out, out


# --------------------------------------------------------------------------- F7 fetch: broken STAC fields


@pytest.fixture
def stac_root(tmp_path):
    root_json, _ = build_catalogue(tmp_path / "stac")
    return root_json


def _edit(path, change):
    d = json.loads(path.read_text())
    change(d)
    path.write_text(json.dumps(d))


def test_fetch_names_links_that_are_not_a_list(stac_root, tmp_path):
    _edit(stac_root, lambda d: d.__setitem__("links", {"a": 1}))
    with pytest.raises(DataError) as e:
        fetch_catalog(stac_root, tmp_path / "out")
    assert e.value.field == "links" and "not a list" in e.value.reason, e.value
    assert "string indices" not in str(e.value)


@pytest.mark.parametrize(
    ("change", "field", "words"),
    [
        (lambda d: d["properties"].__setitem__("datetime", 1687000000), "properties.datetime", "not an RFC 3339"),
        (lambda d: d["properties"].__setitem__("datetime", "yesterday"), "properties.datetime", "not an RFC 3339"),
        (lambda d: d["links"].append({"rel": "child"}), "links[3].href", "missing"),
        (lambda d: d.__setitem__("assets", []), "assets", "not an object"),
    ],
    ids=["datetime-int", "datetime-text", "link-without-href", "assets-list"],
)
def test_fetch_names_the_broken_field_of_an_item_and_fetches_the_others(stac_root, tmp_path, change, field, words):
    _edit(item_json(stac_root.parent, "BE36", "118750"), change)
    rep = fetch_catalog(stac_root, tmp_path / "out", heliostats=["BE36"])
    assert len(rep.failed) == 1 and rep.failed[0][0].endswith("118750.json"), rep.failed
    assert f"field '{field}': {words}" in rep.failed[0][1], rep.failed
    assert "has no len" not in rep.failed[0][1] and "not a valid STAC object" not in rep.failed[0][1]
    assert len(rep.downloaded) == 4  # tower, properties, the two other calibration records


def test_fetch_names_an_asset_without_href_and_fetches_the_rest(stac_root, tmp_path, capsys):
    _edit(item_json(stac_root.parent, "BE36", "118750"), lambda d: d["assets"]["calibration_properties"].pop("href"))
    rep = fetch_catalog(stac_root, tmp_path / "out", heliostats=["BE36"])
    assert len(rep.failed) == 1 and "field 'assets.calibration_properties.href': missing" in rep.failed[0][1]
    assert len(rep.downloaded) == 4
    rc, _, err = run_cli(["fetch", str(stac_root), "--out", str(tmp_path / "o2"), "--quiet"], capsys)
    assert rc == 2 and "'assets.calibration_properties.href': missing" in err and "Traceback" not in err, err


# --------------------------------------------------------------------------- F5 duplicated facets


def _properties_file():
    return next(hj.default_data_dir().glob("*/Properties/*-heliostat-properties.json"))


def test_facets_listed_many_times_are_refused(tmp_path):
    src = _properties_file()
    d = json.loads(src.read_text())
    fp = d["facet_properties"]
    n = len(fp["facets"])
    fp["facets"] *= 25
    fp["number_of_facets"] = 25 * n
    bad = tmp_path / src.name
    bad.write_text(json.dumps(d))
    for read in (read_heliostat_properties, read_facets):
        with pytest.raises(DataError) as e:
            read(bad)
        assert e.value.field == f"facet_properties.facets[{n}].translation_vector", e.value
        assert "overlaps facet 0" in e.value.reason and str(bad) in str(e.value)


def test_more_facets_than_fit_the_heliostat_are_flagged(tmp_path):
    """Flagged, not refused: a damaged width (5e-324 m) would otherwise refuse a
    heliostat whose facets are right (that width is flagged against the fleet,
    tests/test_cli_hostile.py); copies at one place are refused (overlap)."""
    src = _properties_file()
    d = json.loads(src.read_text())
    fp = d["facet_properties"]
    spread = []
    for k in range(4):  # copies side by side: no overlap, 4 times the area
        for f in json.loads(src.read_text())["facet_properties"]["facets"]:
            f["translation_vector"][0] += 5.0 * k
            spread.append(f)
    fp["facets"], fp["number_of_facets"] = spread, len(spread)
    bad = tmp_path / src.name
    bad.write_text(json.dumps(d))
    notes = dict(read_heliostat_properties(bad).notes)
    assert "do not fit" in notes["facet_properties.facets"], notes


def test_embedded_properties_still_load():
    files = sorted(hj.default_data_dir().glob("*/Properties/*-heliostat-properties.json"))
    assert files
    for f in files:
        assert len(read_heliostat_properties(f).facets) == 4


def test_shared_properties_still_load(shared_paint):
    files = sorted(shared_paint.rglob("*-heliostat-properties.json"))
    assert files
    for f in files:
        assert len(read_heliostat_properties(f).facets) >= 1
