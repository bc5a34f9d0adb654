"""STAC fetch: a small PAINT-style catalogue built with pystac, read from a path and over HTTP."""

from __future__ import annotations

import argparse
import contextlib
import csv
import datetime as dt
import functools
import hashlib
import http.server
import io
import json
import os
import threading
from collections.abc import Iterator
from pathlib import Path

import pystac
import pytest

import heliojax as hj
from heliojax._errors import DataError
from heliojax.cli import _fetch as fetch_cli
from heliojax.paint import JOURNAL_NAME, fetch_catalog, verify_download

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "paint"
UTC = dt.UTC


# --------------------------------------------------------------------------- fixtures
def _source_records() -> dict:
    """{heliostat: {"properties": bytes, "items": [(id, datetime, {asset_key: (name, bytes)})]}}
    from the shared PAINT data (or synthetic stand-ins when it is absent)."""
    out: dict = {}
    if (SHARED / "BE36").is_dir() and (SHARED / "flux-samples" / "AA31").is_dir():
        stamps = json.loads((SHARED / "calibration-timestamps.json").read_text())
        be = SHARED / "BE36"
        items = []
        for cid in ("118671", "118750", "118826"):
            when = dt.datetime.fromisoformat(stamps[cid]["datetime"].replace("Z", "+00:00"))
            name = f"{cid}-calibration-properties.json"
            items.append((cid, when, {"calibration_properties": (name, (be / "Calibration" / name).read_bytes())}))
        out["BE36"] = {
            "properties": (be / "Properties" / "BE36-heliostat-properties.json").read_bytes(),
            "items": items,
        }
        aa = SHARED / "flux-samples" / "AA31"
        items = []
        for k, cid in enumerate(("125284", "126372")):
            assets = {
                "calibration_properties": (f"{cid}-calibration-properties.json", None),
                "flux_image": (f"{cid}-flux.png", None),
                "flux_centered_image": (f"{cid}-flux-centered.png", None),
            }
            assets = {key: (n, (aa / "Calibration" / n).read_bytes()) for key, (n, _) in assets.items()}
            items.append((cid, dt.datetime(2022, 7, 1 + 10 * k, 12, tzinfo=UTC), assets))
        out["AA31"] = {
            "properties": (aa / "Properties" / "AA31-heliostat-properties.json").read_bytes(),
            "items": items,
        }
        tower = (SHARED / "WRI1030197-tower-measurements.json").read_bytes()
    else:  # synthetic stand-ins with the same names

        def rec(i):
            return json.dumps({"sun_azimuth": -40.0 + i, "sun_elevation": 30.0, "motor_position": {}}).encode()

        out["BE36"] = {
            "properties": b'{"heliostat_position": [50.9, 6.38, 88.0]}',
            "items": [
                (
                    cid,
                    when,  # the real records' times, as with ../shared
                    {"calibration_properties": (f"{cid}-calibration-properties.json", rec(i))},
                )
                for i, (cid, when) in enumerate(
                    (
                        ("118671", dt.datetime(2022, 6, 12, 13, 27, 37, tzinfo=UTC)),
                        ("118750", dt.datetime(2022, 6, 12, 13, 45, 35, tzinfo=UTC)),
                        ("118826", dt.datetime(2022, 6, 12, 14, 0, 56, tzinfo=UTC)),
                    )
                )
            ],
        }
        out["AA31"] = {
            "properties": b'{"heliostat_position": [50.9, 6.38, 89.0]}',
            "items": [
                (
                    cid,
                    dt.datetime(2022, 7, 1 + 10 * k, 12, tzinfo=UTC),
                    {
                        "calibration_properties": (f"{cid}-calibration-properties.json", rec(k)),
                        "flux_image": (f"{cid}-flux.png", b"\x89PNG\r\n\x1a\n-flux" + bytes(200 + k)),
                        "flux_centered_image": (
                            f"{cid}-flux-centered.png",
                            b"\x89PNG\r\n\x1a\n-centered" + bytes(300 + k),
                        ),
                    },
                )
                for k, cid in enumerate(("125284", "126372"))
            ],
        }
        tower = b'{"power_plant_properties": {"ID": "WRI1030197", "coordinates": [50.9, 6.38, 87.0]}}'
    return {"heliostats": out, "tower": tower}


def multihash_sha256(data: bytes) -> str:
    return "1220" + hashlib.sha256(data).hexdigest()


def _extent():
    return pystac.Extent(
        pystac.SpatialExtent([[6.38, 50.91, 6.39, 50.92]]),
        pystac.TemporalExtent([[dt.datetime(2022, 1, 1, tzinfo=UTC), None]]),
    )


def _embedded_records() -> dict:
    """:func:`_source_records`' structure for every record of the embedded PAINT subset."""
    data = hj.default_data_dir()
    stamps = json.loads((data / "calibration-timestamps.json").read_text())
    out: dict = {}
    for hid in sorted(p.name for p in data.iterdir() if (p / "Properties").is_dir()):
        items = []
        for f in sorted((data / hid / "Calibration").glob("*-calibration-properties.json")):
            cid = f.name.split("-")[0]
            when = dt.datetime.fromisoformat(stamps[cid]["datetime"].replace("Z", "+00:00"))
            items.append((cid, when, {"calibration_properties": (f.name, f.read_bytes())}))
        props = (data / hid / "Properties" / f"{hid}-heliostat-properties.json").read_bytes()
        out[hid] = {"properties": props, "items": items}
    return {"heliostats": out, "tower": (data / "WRI1030197-tower-measurements.json").read_bytes()}


def build_catalogue(root_dir: Path, src: dict | None = None) -> tuple[Path, dict]:
    """PAINT-like catalogue: root -> tower item, weather collection, heliostat catalogues ->
    properties / calibration collections -> items -> assets. BE36's assets carry
    file:size and file:checksum; AA31's do not. Returns (root json path, expected files)."""
    src = _source_records() if src is None else src
    root = pystac.Catalog("WRI1030197-catalog", "PAINT test catalogue")
    tower = pystac.Item("WRI1030197-tower-measurements", None, None, dt.datetime(2020, 10, 7, tzinfo=UTC), {})
    root.add_item(tower)
    root.add_child(pystac.Collection("weather-collection", "ignored", _extent()))
    pending = []  # (item, key, name, data, with_file_ext)
    expected: dict[str, bytes] = {"WRI1030197-tower-measurements.json": src["tower"]}
    pending.append((tower, "measurements", "WRI1030197-tower-measurements.json", src["tower"], False))
    for hid, rec in src["heliostats"].items():
        cat = pystac.Catalog(f"{hid}-heliostat-catalog", f"heliostat {hid}")
        root.add_child(cat)
        props = pystac.Collection(f"{hid}-heliostat-properties-collection", "props", _extent())
        calib = pystac.Collection(f"{hid}-calibration-collection", "calib", _extent())
        cat.add_child(props)
        cat.add_child(calib)
        pitem = pystac.Item(f"{hid}-heliostat-properties", None, None, dt.datetime(2021, 1, 1, tzinfo=UTC), {})
        props.add_item(pitem)
        name = f"{hid}-heliostat-properties.json"
        pending.append((pitem, "heliostat-properties", name, rec["properties"], hid == "BE36"))
        expected[f"{hid}/Properties/{name}"] = rec["properties"]
        for cid, when, assets in rec["items"]:
            item = pystac.Item(cid, None, None, when, {})
            calib.add_item(item)
            for key, (name, data) in assets.items():
                pending.append((item, key, name, data, hid == "BE36"))
                expected[f"{hid}/Calibration/{name}"] = data
    root.normalize_hrefs(str(root_dir))
    for item, key, name, data, with_ext in pending:
        path = Path(item.get_self_href()).parent / "data" / name  # beside the item JSON, never onto it
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        extra = {"file:size": len(data), "file:checksum": multihash_sha256(data)} if with_ext else {}
        item.add_asset(key, pystac.Asset(str(path), media_type="application/json", extra_fields=extra))
    root.make_all_asset_hrefs_relative()
    root.save(pystac.CatalogType.SELF_CONTAINED)
    return root_dir / "catalog.json", expected


def item_json(root_dir: Path, hid: str, item_id: str) -> Path:
    return root_dir / f"{hid}-heliostat-catalog" / f"{hid}-calibration-collection" / item_id / f"{item_id}.json"


def edit_asset(root_dir: Path, hid: str, item_id: str, key: str, **fields) -> None:
    p = item_json(root_dir, hid, item_id)
    d = json.loads(p.read_text())
    d["assets"][key].update(fields)
    p.write_text(json.dumps(d))


@pytest.fixture
def catalogue(tmp_path):
    root_json, expected = build_catalogue(tmp_path / "stac")
    return root_json, expected


@contextlib.contextmanager
def serve(directory: Path, log: list | None = None, errors: dict | None = None, agents: set | None = None):
    """Static HTTP server on 127.0.0.1 (ephemeral port) in a thread; shut down on exit. ``log``
    gets each request's path, ``agents`` each User-Agent; ``errors`` maps a path to the answers
    given, one per request, before the file is served (0: the connection is closed unanswered)."""
    lock = threading.Lock()

    class Handler(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):  # keep test output clean
            pass

        def do_GET(self):
            with lock:
                if log is not None:
                    log.append(self.path)
                if agents is not None:
                    agents.add(self.headers.get("User-Agent"))
                queued = (errors or {}).get(self.path)
                code = queued.pop(0) if queued else None
            if code == 0:
                self.close_connection = True
            elif code is not None:
                self.send_error(code)
            else:
                super().do_GET()

    with _http_server(functools.partial(Handler, directory=str(directory))) as url:
        yield url


@contextlib.contextmanager
def _http_server(handler, host: str = "127.0.0.1") -> Iterator[str]:
    """A threading HTTP server of ``handler`` on ``host`` (a loopback address); yields its base URL."""
    srv = http.server.ThreadingHTTPServer((host, 0), handler)
    srv.daemon_threads = True
    th = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    th.start()
    try:
        yield f"http://{host}:{srv.server_address[1]}"
    finally:
        srv.shutdown()
        srv.server_close()
        th.join(timeout=5)


ALL_CAL = ("calibration_properties", "flux_image", "flux_centered_image")


def files_under(out: Path) -> dict[str, bytes]:
    """The downloaded files (without the calibration-timestamps.json that fetch
    writes from the items' datetimes)."""
    return {
        p.relative_to(out).as_posix(): p.read_bytes()
        for p in out.rglob("*")
        if p.is_file() and not p.name.startswith(".") and p.name != "calibration-timestamps.json"
    }


# --------------------------------------------------------------------------- tests
def test_fetch_from_path_writes_paint_layout(catalogue, tmp_path):
    root_json, expected = catalogue
    out = tmp_path / "out"
    msgs: list[str] = []
    rep = fetch_catalog(root_json, out, calibration_assets=ALL_CAL, progress=msgs.append)
    assert rep.ok and rep.failed == () and rep.missing == ()
    assert rep.heliostats == ("AA31", "BE36")
    assert files_under(out) == expected  # byte-identical, PAINT layout, nothing else
    stamps = json.loads((out / "calibration-timestamps.json").read_text())  # the items' datetimes
    assert stamps == {
        "118671": {"heliostat_id": "BE36", "datetime": "2022-06-12T13:27:37Z"},
        "118750": {"heliostat_id": "BE36", "datetime": "2022-06-12T13:45:35Z"},
        "118826": {"heliostat_id": "BE36", "datetime": "2022-06-12T14:00:56Z"},
        "125284": {"heliostat_id": "AA31", "datetime": "2022-07-01T12:00:00Z"},
        "126372": {"heliostat_id": "AA31", "datetime": "2022-07-11T12:00:00Z"},
    }
    assert "BE36/Calibration/118671-calibration-properties.json" in expected
    assert len(rep.downloaded) == len(expected) and rep.skipped == ()
    assert rep.bytes_downloaded == sum(len(b) for b in expected.values())
    assert verify_download(out) == []
    assert not list(out.rglob("*.part"))
    assert any("[2/2] BE36" in m for m in msgs) and msgs[-1].startswith("done:")
    # the folder named by the catalogue's own folder also works, and a second run skips all
    rep2 = fetch_catalog(root_json.parent, out, calibration_assets=ALL_CAL)
    assert rep2.downloaded == () and len(rep2.skipped) == len(expected)
    rep3 = fetch_catalog(root_json.as_uri(), tmp_path / "out3", calibration_assets=ALL_CAL)  # file:// URL
    assert rep3.ok and files_under(tmp_path / "out3") == expected


def test_fetched_folder_matches_shared_layout(catalogue, tmp_path):
    if not (SHARED / "BE36").is_dir():
        pytest.skip(f"shared PAINT data not found at {SHARED}")
    root_json, _ = catalogue
    out = tmp_path / "out"
    fetch_catalog(root_json, out, heliostats=["BE36"])
    for rel in (
        "BE36/Properties/BE36-heliostat-properties.json",
        "BE36/Calibration/118671-calibration-properties.json",
        "WRI1030197-tower-measurements.json",
    ):
        assert (out / rel).read_bytes() == (SHARED / rel).read_bytes()


def test_fetch_over_http_with_filters(catalogue, tmp_path):
    root_json, expected = catalogue
    out = tmp_path / "out"
    with serve(root_json.parent) as url:
        rep = fetch_catalog(
            f"{url}/catalog.json",
            out,
            heliostats=["AA31", "ZZ99"],
            calibration_assets=("calibration_properties", "flux_image"),
            start=dt.date(2022, 7, 1),
            end=dt.date(2022, 7, 31),
            max_items=1,
            include_tower=False,
        )
    assert rep.missing == ("ZZ99",) and not rep.ok and rep.failed == ()
    assert rep.heliostats == ("AA31",)
    want = {
        "AA31/Properties/AA31-heliostat-properties.json",
        "AA31/Calibration/125284-calibration-properties.json",  # the earliest item only
        "AA31/Calibration/125284-flux.png",
    }
    got = files_under(out)
    assert set(got) == want
    assert all(got[k] == expected[k] for k in want)


def test_only_unknown_heliostats_is_an_error_and_writes_nothing(catalogue, tmp_path):
    root_json, _ = catalogue
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="heliostats: none of ZZ98, ZZ99"):
        fetch_catalog(root_json, out, heliostats=["ZZ99", "ZZ98"])
    assert not out.exists()  # not even the tower file, nor an empty folder


def test_heliostat_catalogues_nested_below_the_root_are_an_error_not_an_empty_fetch(catalogue, tmp_path):
    root_json, _ = catalogue
    root = json.loads(root_json.read_text())
    children = [link for link in root["links"] if link["rel"] == "child"]
    wrapper = {"type": "Catalog", "id": "deeper", "stac_version": "1.1.0", "description": "one level down"}
    wrapper["links"] = [{"rel": "child", "href": "../" + link["href"].removeprefix("./")} for link in children]
    (root_json.parent / "deeper").mkdir()
    (root_json.parent / "deeper" / "catalog.json").write_text(json.dumps(wrapper))
    root["links"] = [link for link in root["links"] if link["rel"] != "child"]
    root["links"].append({"rel": "child", "href": "./deeper/catalog.json"})
    root_json.write_text(json.dumps(root))
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="no heliostat catalogue"):  # was: exit 0, the tower file alone
        fetch_catalog(root_json, out)
    assert not out.exists()


def test_a_percent_encoded_relative_href_reads_the_local_file(catalogue, tmp_path):
    root_json, expected = catalogue
    edit_asset(
        root_json.parent,
        "AA31",
        "126372",
        "calibration_properties",
        href="./data/./126372%2Dcalibration-properties.json",
    )
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"])
    assert not rep.failed  # was: the file "126372%2Dcalibration-properties.json" was looked for
    name = "AA31/Calibration/126372-calibration-properties.json"
    assert (tmp_path / "out" / name).read_bytes() == expected[name]


def test_date_filter_excludes_items_but_keeps_properties(catalogue, tmp_path):
    root_json, _ = catalogue
    out = tmp_path / "out"
    rep = fetch_catalog(root_json, out, heliostats=["AA31"], start=dt.datetime(2022, 7, 5), include_tower=False)
    assert set(files_under(out)) == {
        "AA31/Properties/AA31-heliostat-properties.json",
        "AA31/Calibration/126372-calibration-properties.json",  # 2022-07-11 only
    }
    assert rep.ok


class FailingTransport:
    """Opens like the default, but fails every asset download after the first ``k``."""

    def __init__(self, k: int, midstream: bool = False):
        self.k, self.midstream, self.n, self.lock = k, midstream, 0, threading.Lock()

    def __call__(self, href, timeout_s):
        if href.endswith(("-calibration-properties.json", ".png")):
            with self.lock:
                self.n += 1
                fail = self.n > self.k
            if fail and not self.midstream:
                raise ConnectionResetError("injected failure")
            if fail:
                return _BrokenStream(open(href, "rb"))
        return open(href, "rb")


class _BrokenStream(io.RawIOBase):
    """Yields the first 10 bytes, then the connection 'drops'."""

    def __init__(self, f):
        self.f, self.sent = f, 0

    def read(self, n=-1):
        if self.sent >= 10:
            self.f.close()
            raise ConnectionResetError("injected drop mid-file")
        data = self.f.read(10)
        self.sent += len(data)
        return data

    def close(self):
        self.f.close()
        super().close()


@pytest.mark.parametrize("midstream", [False, True])
def test_interrupted_run_resumes(catalogue, tmp_path, midstream):
    root_json, expected = catalogue
    out = tmp_path / "out"
    n_cal = sum(1 for k in expected if "/Calibration/" in k)
    rep = fetch_catalog(
        root_json, out, calibration_assets=ALL_CAL, transport=FailingTransport(3, midstream), workers=3, retries=0
    )
    assert len(rep.failed) == n_cal - 3 and not rep.ok
    assert all("injected" in reason for _, reason in rep.failed)
    got = files_under(out)
    assert sum("/Calibration/" in k for k in got) == 3
    assert all(got[k] == expected[k] for k in got)  # nothing half-written under a real name
    assert not list(out.rglob("*.part"))
    # A killed process can leave a stale temporary file and, from other tools, a truncated file.
    aa_props = out / "AA31/Properties/AA31-heliostat-properties.json"  # AA31: no file:size/checksum
    aa_props.write_bytes(expected["AA31/Properties/AA31-heliostat-properties.json"][:20])
    stale = out / "AA31/Calibration/.125284-flux.png.abc123.part"
    stale.write_bytes(b"partial")
    rep2 = fetch_catalog(root_json, out, calibration_assets=ALL_CAL)
    assert rep2.ok
    assert len(rep2.downloaded) == n_cal - 3 + 1  # the failed ones + the truncated file
    assert len(rep2.skipped) == len(expected) - len(rep2.downloaded)
    assert files_under(out) == expected
    assert not stale.exists()
    assert verify_download(out) == []


def test_transient_errors_are_retried(catalogue, tmp_path):
    root_json, expected = catalogue
    seen: set[str] = set()
    lock = threading.Lock()

    def flaky(href, timeout_s):  # every file fails once, then works
        with lock:
            first = href not in seen
            seen.add(href)
        if first:
            raise TimeoutError("injected timeout")
        return open(href, "rb")

    out = tmp_path / "out"
    rep = fetch_catalog(root_json, out, calibration_assets=ALL_CAL, transport=flaky, retries=1)
    assert rep.ok and files_under(out) == expected
    with pytest.raises(DataError, match="injected timeout"):
        fetch_catalog(root_json, tmp_path / "out2", transport=lambda h, t: flaky(str(tmp_path / "x"), t), retries=0)


def test_http_retries_server_errors_but_not_404(catalogue, tmp_path):
    """Over real HTTP (requests, urllib3's Retry): a dropped connection and answers 503 are
    retried until the file comes; a 404 is asked for once and listed in ``failed``, and so is
    a 503 that outlasts the retries; everything else is fetched."""
    root_json, expected = catalogue
    stac = root_json.parent
    url_path = {p.name: "/" + p.relative_to(stac).as_posix() for p in stac.rglob("data/*")}
    tower = url_path["WRI1030197-tower-measurements.json"]
    flaky = url_path["118671-calibration-properties.json"]
    gone = url_path["125284-flux.png"]
    down = url_path["126372-flux.png"]
    (stac / gone[1:]).unlink()
    errors = {"/catalog.json": [503], tower: [0], flaky: [503, 503], down: [503, 503, 503]}
    log: list[str] = []
    agents: set[str] = set()
    with serve(stac, log, errors, agents) as url:
        rep = fetch_catalog(f"{url}/catalog.json", tmp_path / "out", calibration_assets=ALL_CAL, retries=2)
    assert [log.count(p) for p in ("/catalog.json", tower, flaky)] == [2, 2, 3]  # retried until they came
    assert log.count(gone) == 1 and log.count(down) == 3  # 404: not retried; 503: two retries, then given up
    reasons = {href.rsplit("/", 1)[-1]: reason for href, reason in rep.failed}
    assert set(reasons) == {"125284-flux.png", "126372-flux.png"} and not rep.ok
    assert "404" in reasons["125284-flux.png"] and "503" in reasons["126372-flux.png"]
    failed = ("125284-flux.png", "126372-flux.png")
    assert files_under(tmp_path / "out") == {k: v for k, v in expected.items() if not k.endswith(failed)}
    assert not list((tmp_path / "out").rglob("*.part"))
    assert agents == {"heliojax-fetch"}


def test_oversized_stac_file_over_http_is_not_read(catalogue, tmp_path, monkeypatch):
    import heliojax.paint._stac_io as stac_io

    root_json, _ = catalogue
    assert root_json.stat().st_size > 100
    monkeypatch.setattr(stac_io, "MAX_STAC_BYTES", 100)
    with serve(root_json.parent) as url:
        with pytest.raises(DataError, match="STAC file larger than 100 bytes") as ei:
            fetch_catalog(f"{url}/catalog.json", tmp_path / "out")
    assert ei.value.file == f"{url}/catalog.json"


def test_resume_redownloads_corrupted_file_with_checksum(catalogue, tmp_path):
    root_json, expected = catalogue
    out = tmp_path / "out"
    fetch_catalog(root_json, out, heliostats=["BE36"])
    target = out / "BE36/Calibration/118750-calibration-properties.json"
    data = bytearray(target.read_bytes())
    data[5] ^= 1  # same size, one bit off: only the checksum can tell
    target.write_bytes(bytes(data))
    assert any("SHA-256" in p for p in verify_download(out))
    rep = fetch_catalog(root_json, out, heliostats=["BE36"])
    assert [p.name for p in rep.downloaded] == ["118750-calibration-properties.json"]
    assert target.read_bytes() == expected["BE36/Calibration/118750-calibration-properties.json"]
    # --no-resume downloads everything again
    rep = fetch_catalog(root_json, out, heliostats=["BE36"], resume=False)
    assert rep.skipped == () and len(rep.downloaded) == 5


def test_resume_over_http_requests_only_missing_files(catalogue, tmp_path):
    root_json, expected = catalogue
    out = tmp_path / "out"
    log: list[str] = []
    with serve(root_json.parent, log) as url:
        fetch_catalog(f"{url}/catalog.json", out, calibration_assets=ALL_CAL)
        (out / "AA31/Calibration/126372-flux.png").unlink()
        log.clear()
        rep = fetch_catalog(f"{url}/catalog.json", out, calibration_assets=ALL_CAL)
    assets = [p for p in log if "/data/" in p]  # STAC JSON requests are not asset requests
    assert [p.rsplit("/", 1)[-1] for p in assets] == ["126372-flux.png"]
    assert len(log) > len(assets)  # the catalogue itself was read again
    assert [p.name for p in rep.downloaded] == ["126372-flux.png"] and rep.ok


def test_checksum_and_size_mismatch_detected(catalogue, tmp_path):
    root_json, _ = catalogue
    edit_asset(root_json.parent, "BE36", "118671", "calibration_properties", **{"file:checksum": "1220" + "00" * 32})
    edit_asset(root_json.parent, "BE36", "118750", "calibration_properties", **{"file:size": 3})
    out = tmp_path / "out"
    rep = fetch_catalog(root_json, out, heliostats=["BE36"])
    reasons = {href.rsplit("/", 1)[-1]: r for href, r in rep.failed}
    assert set(reasons) == {"118671-calibration-properties.json", "118750-calibration-properties.json"}
    assert "checksum mismatch" in reasons["118671-calibration-properties.json"]
    assert "size" in reasons["118750-calibration-properties.json"]
    assert not (out / "BE36/Calibration/118671-calibration-properties.json").exists()
    assert not (out / "BE36/Calibration/118750-calibration-properties.json").exists()
    assert (out / "BE36/Calibration/118826-calibration-properties.json").exists()
    assert not list(out.rglob("*.part")) and not rep.ok


def test_unreadable_item_is_reported_and_the_rest_fetched(catalogue, tmp_path):
    root_json, expected = catalogue
    p = item_json(root_json.parent, "BE36", "118750")
    good = p.read_bytes()
    p.write_bytes(b"{not json")
    out = tmp_path / "out"
    rep = fetch_catalog(root_json, out, heliostats=["BE36"])
    assert len(rep.failed) == 1 and rep.failed[0][0].endswith("118750.json") and "not a JSON file" in rep.failed[0][1]
    assert not rep.ok and len(rep.downloaded) == 4  # tower, properties, two calibration records
    p.write_bytes(good)
    rep = fetch_catalog(root_json, out, heliostats=["BE36"])
    assert rep.ok and [q.name for q in rep.downloaded] == ["118750-calibration-properties.json"]


def test_what_the_catalogue_lacks_for_calibrate_is_said(catalogue, tmp_path):
    """Every planned download succeeds, yet the folder cannot be calibrated: an item
    without assets, a tower item without its file, a properties item without its file.
    The fetch used to end with 0 failed and no word."""
    root_json, _ = catalogue
    root = root_json.parent
    assert fetch_catalog(root_json, tmp_path / "complete", heliostats=["BE36"]).warnings == ()
    for path in (
        item_json(root, "BE36", "118750"),
        next(root.rglob("WRI1030197-tower-measurements.json")),
        next(root.rglob("BE36-heliostat-properties/BE36-heliostat-properties.json")),
    ):
        d = json.loads(path.read_text())
        d["assets"] = {}
        path.write_text(json.dumps(d))
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["BE36"])
    assert rep.ok and not rep.failed
    said = "\n".join(rep.warnings)
    assert "no tower file (*-tower-measurements.json)" in said, said
    assert "BE36: calibration records but no properties file" in said, said
    assert "1 calibration record(s) with a time but no calibration-properties file (e.g. record 118750" in said, said


@pytest.mark.parametrize(
    ("field", "value"),
    [("file:size", -1), ("file:size", "big"), ("file:checksum", "zz"), ("href", ""), ("href", 5)],
)
def test_an_asset_with_broken_metadata_fails_alone(catalogue, tmp_path, field, value):
    """Broken (not hostile) asset metadata fails that file; the other files are fetched."""
    root_json, _ = catalogue
    edit_asset(root_json.parent, "BE36", "118750", "calibration_properties", **{field: value})
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["BE36"])
    assert len(rep.failed) == 1 and rep.failed[0][0].endswith("118750.json"), rep.failed
    assert f"assets.calibration_properties.{field}" in rep.failed[0][1] or field == "href", rep.failed
    assert len(rep.downloaded) == 4  # tower, properties, the two other calibration records


def test_invalid_json_asset_is_not_kept(catalogue, tmp_path):
    root_json, _ = catalogue
    p = item_json(root_json.parent, "AA31", "125284").parent / "data" / "125284-calibration-properties.json"
    p.write_bytes(b'{"truncated": ')
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"])
    assert len(rep.failed) == 1 and "does not parse" in rep.failed[0][1]
    assert not (tmp_path / "out/AA31/Calibration/125284-calibration-properties.json").exists()


@pytest.mark.parametrize(
    "href, message",
    [
        ("../../../../outside/evil.json", "outside the catalogue folder"),
        ("%2e%2e/%2e%2e/%2e%2e/%2e%2e/outside/evil.json", "outside the catalogue folder"),
        ("https://example.org/data/../../evil.json", "'..' segment"),
        ("sub%2Fevil.json", "unsafe or empty file name"),
        (".hidden.json", "unsafe or empty file name"),
        ("ftp://example.org/evil.json", "not supported"),
        ("file:///etc/hostname", "outside the catalogue folder"),
        ("ABSOLUTE_OUTSIDE", "outside the catalogue folder"),
    ],
)
def test_unsafe_hrefs_are_refused(catalogue, tmp_path, href, message):
    root_json, _ = catalogue
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "evil.json").write_text("{}")
    if href == "ABSOLUTE_OUTSIDE":
        href = str(outside / "evil.json")
    edit_asset(root_json.parent, "AA31", "126372", "calibration_properties", href=href)
    out = tmp_path / "out"
    with pytest.raises(DataError, match=message) as ei:
        fetch_catalog(root_json, out, heliostats=["AA31"])
    assert ei.value.field == "assets.calibration_properties.href"
    assert ei.value.file.endswith("126372.json")
    assert not out.exists()  # refused before anything was written, the tower file neither
    assert sorted(p.name for p in tmp_path.rglob("evil.json")) == ["evil.json"]


def test_an_unsafe_href_of_a_later_heliostat_leaves_nothing_written(catalogue, tmp_path):
    """The tower file and the heliostats planned before an unsafe href were written
    before it was refused (hostile-input trial 4): every file is planned first now."""
    root_json, _ = catalogue
    edit_asset(root_json.parent, "BE36", "118750", "calibration_properties", href="../../../../outside/x.json")
    out = tmp_path / "out"
    with pytest.raises(DataError, match="outside the catalogue folder"):
        fetch_catalog(root_json, out)
    assert not out.exists()


def test_a_relative_href_that_climbs_within_the_catalogue_is_fetched(catalogue, tmp_path):
    """``..`` in a relative asset href was refused even where it stays inside the
    catalogue's folder (a static catalogue that keeps assets beside its collections)."""
    root_json, expected = catalogue
    item = item_json(root_json.parent, "AA31", "126372")
    name = "126372-calibration-properties.json"
    shared = item.parent.parent / "assets"
    shared.mkdir()
    (item.parent / "data" / name).rename(shared / name)
    edit_asset(root_json.parent, "AA31", "126372", "calibration_properties", href=f"../assets/{name}")
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"])
    assert not rep.failed, rep.failed
    assert (tmp_path / "out" / "AA31" / "Calibration" / name).read_bytes() == expected[f"AA31/Calibration/{name}"]


def test_symlinked_source_leaving_catalogue_is_refused(catalogue, tmp_path):
    root_json, _ = catalogue
    secret = tmp_path / "secret.json"
    secret.write_text('{"secret": 1}')
    link_dir = item_json(root_json.parent, "AA31", "126372").parent
    (link_dir / "data" / "linked.json").symlink_to(secret)
    edit_asset(root_json.parent, "AA31", "126372", "calibration_properties", href="./data/linked.json")
    with pytest.raises(DataError, match="outside the catalogue folder"):
        fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"])


def test_symlink_in_output_is_refused(catalogue, tmp_path):
    root_json, _ = catalogue
    out = tmp_path / "out"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / "AA31").mkdir(parents=True)
    (out / "AA31" / "Calibration").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(DataError, match="symbolic link"):
        fetch_catalog(root_json, out, heliostats=["AA31"])
    assert list(elsewhere.iterdir()) == []


def test_remote_catalogue_may_not_point_at_local_files(catalogue, tmp_path):
    root_json, _ = catalogue
    local = tmp_path / "local.json"
    local.write_text("{}")
    edit_asset(root_json.parent, "AA31", "126372", "calibration_properties", href=local.as_uri())
    with serve(root_json.parent) as url:
        with pytest.raises(DataError, match="remote catalogue may not point at local files"):
            fetch_catalog(f"{url}/catalog.json", tmp_path / "out", heliostats=["AA31"])


def test_missing_catalogue_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="not found"):
        fetch_catalog(tmp_path / "nope.json", tmp_path / "out")
    with serve(tmp_path) as url:
        with pytest.raises(DataError, match="cannot read STAC file"):
            fetch_catalog(f"{url}/nope.json", tmp_path / "out", retries=0)


def _cli(argv):
    parser = argparse.ArgumentParser(prog="heliojax")
    fetch_cli.add_parser(parser.add_subparsers(dest="command", required=True))
    return fetch_cli.run(parser.parse_args(argv))


def test_cli(catalogue, tmp_path, capsys):
    root_json, expected = catalogue
    out = tmp_path / "out"
    assert _cli(["fetch", str(root_json), "--out", str(out), "--assets", "all", "--start", "2022-01-01"]) == 0
    err = capsys.readouterr().err
    assert "[1/2] AA31" in err and "done:" in err
    assert files_under(out) == expected
    assert (out / JOURNAL_NAME).exists()
    assert _cli(["fetch", str(root_json), "--out", str(out), "--heliostats", "BE36,XX01", "--quiet"]) == 2
    assert "XX01" in capsys.readouterr().err
    edit_asset(root_json.parent, "BE36", "118671", "calibration_properties", href="../../../../evil.json")
    assert _cli(["fetch", str(root_json), "--out", str(out), "--no-resume", "--quiet"]) == 2
    assert "path traversal" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _cli(["fetch", str(root_json), "--out", str(out), "--start", "yesterday"])


def test_downloaded_files_are_world_readable_per_umask(catalogue, tmp_path):
    root_json, _ = catalogue
    out = tmp_path / "out"
    fetch_catalog(root_json, out, heliostats=["BE36"], include_tower=False)
    mask = os.umask(0)
    os.umask(mask)
    mode = (out / "BE36/Properties/BE36-heliostat-properties.json").stat().st_mode & 0o777
    assert mode == 0o666 & ~mask


def _write_paint_style(site: Path, base: str, records: dict) -> dict[str, bytes]:
    """The PAINT server's own naming: ``<base>/WRI1030197-catalog-stac.json`` etc., every
    link and asset an absolute http URL (as on paint-database.org)."""
    p = "WRI1030197"
    stac_version = "1.0.0"

    def link(rel, href):
        return {"rel": rel, "href": f"{base}/{href}", "type": "application/geo+json"}

    def put(rel_path, obj):
        f = site / rel_path
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(obj if isinstance(obj, bytes) else json.dumps(obj).encode())

    def catalog(cid, links):
        return {"type": "Catalog", "stac_version": stac_version, "id": cid, "description": cid, "links": links}

    def collection(cid, links):
        return {
            "type": "Collection",
            "stac_version": stac_version,
            "id": cid,
            "description": cid,
            "license": "CDLA-2.0",
            "extent": {
                "spatial": {"bbox": [[6.38, 50.91, 6.39, 50.92]]},
                "temporal": {"interval": [["2021-01-01T00:00:00Z", None]]},
            },
            "links": links,
        }

    def item(iid, when, assets, self_href):
        return {
            "type": "Feature",
            "stac_version": stac_version,
            "id": iid,
            "geometry": None,
            "properties": {"datetime": when},
            "links": [link("self", self_href)],
            "assets": {k: {"href": f"{base}/{h}", "roles": ["data"]} for k, h in assets.items()},
        }

    expected: dict[str, bytes] = {}
    put(f"{p}-tower-measurements.json", records["tower"])
    expected[f"{p}-tower-measurements.json"] = records["tower"]
    put(
        f"{p}-tower-measurements-item-stac.json",
        item(
            f"{p}-tower-measurements",
            "2020-10-07T00:00:00Z",
            {"measurements": f"{p}-tower-measurements.json"},
            f"{p}-tower-measurements-item-stac.json",
        ),
    )
    root_links = [
        link("self", f"{p}-catalog-stac.json"),
        link("child", "Weather/weather-collection-stac.json"),
        link("child", f"{p}-tower-measurements-item-stac.json"),
    ]
    rec = records["heliostats"]["BE36"]
    h = "BE36"
    root_links.append(link("child", f"{h}/{h}-heliostat-catalog-stac.json"))
    put(
        f"{h}/{h}-heliostat-catalog-stac.json",
        catalog(
            f"{h}-heliostat-catalog",
            [
                link("child", f"{h}/Deflectometry/{h}-deflectometry-collection-stac.json"),
                link("child", f"{h}/Calibration/{h}-calibration-collection-stac.json"),
                link("child", f"{h}/Properties/{h}-heliostat-properties-collection-stac.json"),
            ],
        ),
    )
    # properties
    put(f"{h}/Properties/{h}-heliostat-properties.json", rec["properties"])
    expected[f"{h}/Properties/{h}-heliostat-properties.json"] = rec["properties"]
    put(
        f"{h}/Properties/{h}-heliostat-properties-item-stac.json",
        item(
            f"{h}-heliostat-properties",
            "2021-01-01T00:00:00Z",
            {"heliostat-properties": f"{h}/Properties/{h}-heliostat-properties.json"},
            f"{h}/Properties/{h}-heliostat-properties-item-stac.json",
        ),
    )
    put(
        f"{h}/Properties/{h}-heliostat-properties-collection-stac.json",
        collection(
            f"{h}-heliostat-properties-collection",
            [link("item", f"{h}/Properties/{h}-heliostat-properties-item-stac.json")],
        ),
    )
    # calibration (raw images listed but not fetched by default)
    cal_links = []
    for cid, when, assets in rec["items"]:
        name, data = assets["calibration_properties"]
        put(f"{h}/Calibration/{name}", data)
        put(f"{h}/Calibration/{cid}-raw.png", b"\x89PNG\r\n\x1a\n raw")
        expected[f"{h}/Calibration/{name}"] = data
        put(
            f"{h}/Calibration/{cid}-calibration-item-stac.json",
            item(
                cid,
                when.strftime("%Y-%m-%dT%H:%M:%SZ"),
                {"raw_image": f"{h}/Calibration/{cid}-raw.png", "calibration_properties": f"{h}/Calibration/{name}"},
                f"{h}/Calibration/{cid}-calibration-item-stac.json",
            ),
        )
        cal_links.append(link("item", f"{h}/Calibration/{cid}-calibration-item-stac.json"))
    put(f"{h}/Calibration/{h}-calibration-collection-stac.json", collection(f"{h}-calibration-collection", cal_links))
    # deflectometry
    h5 = f"{h}-2023-09-18Z08-32-29Z-deflectometry.h5"
    put(f"{h}/Deflectometry/{h5}", b"\x89HDF\r\n\x1a\n" + bytes(64))
    expected[f"{h}/Deflectometry/{h5}"] = b"\x89HDF\r\n\x1a\n" + bytes(64)
    put(
        f"{h}/Deflectometry/{h}-defl-item-stac.json",
        item(
            f"{h}-2023-09-18Z08-32-29Z",
            "2023-09-18T08:32:29Z",
            {"raw_measurement": f"{h}/Deflectometry/{h5}"},
            f"{h}/Deflectometry/{h}-defl-item-stac.json",
        ),
    )
    put(
        f"{h}/Deflectometry/{h}-deflectometry-collection-stac.json",
        collection(f"{h}-deflectometry-collection", [link("item", f"{h}/Deflectometry/{h}-defl-item-stac.json")]),
    )
    put(f"{p}-catalog-stac.json", catalog(f"{p}-catalog", root_links))
    return expected


def test_paint_style_catalogue_with_absolute_urls(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    log: list[str] = []
    with serve(site, log) as url:
        base = f"{url}/WRI1030197"
        expected = _write_paint_style(site / "WRI1030197", base, _source_records())
        out = tmp_path / "out"
        rep = fetch_catalog(
            f"{base}/WRI1030197-catalog-stac.json", out, collections=("properties", "calibration", "deflectometry")
        )
    assert rep.ok and rep.heliostats == ("BE36",)
    assert files_under(out) == expected  # no raw images, PAINT layout, tower at the root
    assert not any("weather" in p for p in log)  # the weather collection is never read


def test_new_user_path_fetch_inspect_calibrate_aim(tmp_path, capsys):
    """A new user's path over HTTP: serve a catalogue of the embedded records on
    127.0.0.1, fetch it, inspect and calibrate it with the defaults (time split from
    the items' datetimes) and aim with the fit: every command exits 0, every heliostat
    is fitted and gets usable commands."""
    from heliojax.cli._main import main

    build_catalogue(tmp_path / "site", _embedded_records())
    out = tmp_path / "fetched"
    with serve(tmp_path / "site") as url:
        assert main(["fetch", f"{url}/catalog.json", "--out", str(out), "--quiet"]) == 0
    assert main(["inspect", str(out), "--cache-dir", "none"]) == 0
    assert "BE36" in capsys.readouterr().out
    report, results = tmp_path / "summary.json", tmp_path / "results.h5"
    argv = ["calibrate", str(out), "--report", str(report), "--out", str(results), "--cache-dir", "none", "--quiet"]
    assert main(argv) == 0
    s = json.loads(report.read_text())
    assert s["split"] == "time" and s["fleet"]["n_heliostats"] == 5
    assert {h["status"] for h in s["heliostats"].values()} == {"converged"}
    assert all(h["n_train"] > 0 and h["n_test"] > 0 for h in s["heliostats"].values())
    aim = tmp_path / "aim.csv"
    # after every heliostat's first fitted record (BL14's fit starts at its 2024-05 change point)
    argv = ["aim", str(results), "--date", "2024-06-21", "--step-minutes", "120", "--out", str(aim), "--quiet"]
    assert main([*argv, "--cache-dir", "none"]) == 0
    with open(aim, newline="") as f:
        rows = list(csv.DictReader(f))
    usable = {r["heliostat_id"] for r in rows if r["ok"] == "1"}
    assert usable == set(s["heliostats"])  # every fitted heliostat gets commands without a flag


def test_lying_content_length_and_damaged_journal_are_clean_errors(tmp_path, capsys):
    """A catalogue whose server announces a huge body and sends a short one is a
    one-line error naming it (no MemoryError), asked for once (a broken-off body is not retried);
    a damaged resume journal is read past."""
    requests_seen: list[str] = []

    class Liar(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            requests_seen.append(self.path)
            self.send_response(200)
            self.send_header("Content-Length", str(10**12))
            self.end_headers()
            self.wfile.write(b'{"type": "Catalog", "id": "x"')
            self.wfile.flush()
            self.close_connection = True

    with _http_server(Liar) as base:
        url = f"{base}/catalog.json"
        rc = _cli(["fetch", url, "--out", str(tmp_path / "o"), "--timeout", "5", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "catalog.json" in err and len(err.strip().splitlines()) <= 2, err
    assert requests_seen == ["/catalog.json"]
    root_json, expected = build_catalogue(tmp_path / "stac")
    out = tmp_path / "out"
    out.mkdir()
    (out / JOURNAL_NAME).write_bytes(b"\xff\xfe garbage\n{not json\n")
    rep = fetch_catalog(root_json, out)
    assert rep.ok and files_under(out) == {k: v for k, v in expected.items() if "flux" not in k}


def test_a_server_that_drips_is_broken_off(tmp_path, capsys):
    """A server that sends a byte now and then, each within the read timeout, holds no
    download for longer than the timeout: slower than MIN_BYTES_PER_S it is an error
    naming the file."""
    import time

    class Drip(http.server.BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Length", "100000")
            self.end_headers()
            try:
                for _ in range(200):  # 40 s at most
                    self.wfile.write(b" ")
                    self.wfile.flush()
                    time.sleep(0.2)
            except OSError:  # the client broke it off
                pass
            self.close_connection = True

    t0 = time.monotonic()
    with _http_server(Drip) as base:
        url = f"{base}/catalog.json"
        rc = _cli(["fetch", url, "--out", str(tmp_path / "o"), "--timeout", "1", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "catalog.json" in err and "bytes/s" in err, err
    assert time.monotonic() - t0 < 10


@contextlib.contextmanager
def _serve_hostile(directory: Path, answers: dict):
    """Static server of ``directory`` where ``answers`` maps a path to ``(body, headers)``."""

    class Handler(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            if self.path not in answers:
                return super().do_GET()
            body, headers = answers[self.path]
            self.send_response(200)
            for k, v in {"Content-Length": str(len(body)), **headers}.items():
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(body)

    with _http_server(functools.partial(Handler, directory=str(directory))) as url:
        yield url


_ITEM = "/AA31-heliostat-catalog/AA31-calibration-collection/126372/126372.json"
_ASSET = "/AA31-heliostat-catalog/AA31-calibration-collection/126372/data/126372-calibration-properties.json"


@pytest.mark.parametrize(
    ("path", "body", "headers", "message"),
    [
        (_ITEM, b'{"a":' * 100_000, {}, "RecursionError"),  # nesting deeper than json's recursion limit
        (_ITEM, b'{"id": ' + b"9" * 5000 + b"}", {}, "ValueError"),  # an int of over 4300 digits
        (_ASSET, b"[" * 100_000, {}, "does not parse"),
        (_ASSET, b"9" * 5000, {}, "does not parse"),
        (_ASSET, __import__("gzip").compress(b"{}" + b" " * (40 * 2**20)), {"Content-Encoding": "gzip"}, "bomb"),
    ],
    ids=["item nested", "item huge int", "asset nested", "asset huge int", "asset gzip bomb"],
)
def test_hostile_server_answers_are_reported_per_file(tmp_path, path, body, headers, message):
    """Answers that break the JSON parser or inflate a few kB to many MB fail that one
    file, named with its reason; the rest of the catalogue is fetched."""
    build_catalogue(tmp_path / "site")
    out = tmp_path / "out"
    with _serve_hostile(tmp_path / "site", {path: (body, headers)}) as url:
        rep = fetch_catalog(f"{url}/catalog.json", out, heliostats=["AA31"], include_tower=False)
    assert len(rep.failed) == 1 and rep.failed[0][0].endswith(path) and message in rep.failed[0][1], rep.failed
    assert (out / "AA31/Calibration/125284-calibration-properties.json").is_file()
    assert not (out / "AA31/Calibration/126372-calibration-properties.json").exists()
    assert not [p for p in out.rglob("*") if p.name.endswith(".part")]


def test_hostile_root_journal_and_naive_datetimes(tmp_path, capsys):
    """A root that breaks the parser is a one-line error and leaves no output folder; a
    resume journal that is a symbolic link is refused (nothing appended through it); an
    item datetime without a time zone is UTC (filtered, and written as such)."""
    build_catalogue(tmp_path / "site")
    item = json.loads((tmp_path / "site" / _ITEM[1:]).read_text())
    item["properties"]["datetime"] = "2022-07-11T12:00:00"  # no zone
    answers = {"/bad.json": (b"[" * 100_000, {}), _ITEM: (json.dumps(item).encode(), {})}
    out = tmp_path / "out"
    with _serve_hostile(tmp_path / "site", answers) as url:
        rc = _cli(["fetch", f"{url}/bad.json", "--out", str(out), "--quiet"])
        err = capsys.readouterr().err
        assert rc == 2 and "bad.json" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists()
        rep = fetch_catalog(f"{url}/catalog.json", out, heliostats=["AA31"], start=dt.date(2022, 7, 5))
        assert rep.ok
        stamps = json.loads((out / "calibration-timestamps.json").read_text())
        assert stamps == {"126372": {"heliostat_id": "AA31", "datetime": "2022-07-11T12:00:00Z"}}
        victim = tmp_path / "victim.txt"
        victim.write_text("v\n")
        other = tmp_path / "other"
        other.mkdir()
        (other / JOURNAL_NAME).symlink_to(victim)
        with pytest.raises(DataError, match="symbolic link"):
            fetch_catalog(f"{url}/catalog.json", other, heliostats=["AA31"])
    assert victim.read_text() == "v\n"


def test_timestamps_name_taken_by_a_folder_is_refused_before_downloading(catalogue, tmp_path):
    root_json, _ = catalogue
    out = tmp_path / "out"
    (out / "calibration-timestamps.json").mkdir(parents=True)
    with pytest.raises(DataError, match="calibration-timestamps.json"):
        fetch_catalog(root_json, out, heliostats=["AA31"])
    assert sorted(p.name for p in out.iterdir()) == ["calibration-timestamps.json"]


@pytest.mark.parametrize("body", [b"<html><body>503 Service Unavailable</body></html>", b""], ids=["html", "empty"])
def test_a_png_answered_with_an_html_page_or_nothing_is_not_kept(tmp_path, body):
    """A flux PNG answered with status 200 and an HTML error page (or an empty body) fails
    that file, named; it is neither kept nor journalled (a resume would skip it for good)."""
    build_catalogue(tmp_path / "site")
    png = _ASSET.replace("calibration-properties.json", "flux.png")
    out = tmp_path / "out"
    with _serve_hostile(tmp_path / "site", {png: (body, {"Content-Type": "image/png"})}) as url:
        rep = fetch_catalog(
            f"{url}/catalog.json", out, heliostats=["AA31"], calibration_assets=ALL_CAL, include_tower=False
        )
    assert len(rep.failed) == 1 and rep.failed[0][0].endswith(png) and "not a PNG" in rep.failed[0][1], rep.failed
    assert not (out / "AA31/Calibration/126372-flux.png").exists()
    assert (out / "AA31/Calibration/125284-flux.png").is_file()
    assert "126372-flux.png" not in (out / JOURNAL_NAME).read_text()


@pytest.mark.parametrize("item_id", ["²", "9" * 5000])
def test_an_item_id_of_odd_digits_is_no_record_id(catalogue, tmp_path, item_id):
    """An item id of digits that int() refuses (a superscript, 5000 digits) gave a bare
    "invalid literal for int()" without a file; it is simply not a record id."""
    root_json, _ = catalogue
    p = item_json(root_json.parent, "AA31", "126372")
    d = json.loads(p.read_text())
    d["id"] = item_id
    data = p.parent / "data"
    (data / "126372-calibration-properties.json").rename(data / "x.json")
    d["assets"]["calibration_properties"]["href"] = "./data/x.json"
    p.write_text(json.dumps(d))
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"])
    assert rep.ok and (tmp_path / "out/AA31/Calibration/x.json").is_file()
    stamps = json.loads((tmp_path / "out/calibration-timestamps.json").read_text())
    assert set(stamps) == {"125284"}


def test_two_items_giving_one_record_keep_its_time_and_are_named(catalogue, tmp_path):
    """Item 126372's asset pointing at 125284's file moved 125284's time to 126372's
    without a word; the first item's time is kept and both items are named."""
    root_json, _ = catalogue
    site = root_json.parent
    other = item_json(site, "AA31", "125284").parent / "data" / "125284-calibration-properties.json"
    edit_asset(site, "AA31", "126372", "calibration_properties", href=str(other))
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"])
    stamps = json.loads((tmp_path / "out/calibration-timestamps.json").read_text())
    assert stamps["125284"]["datetime"] == "2022-07-01T12:00:00Z"
    assert any("125284" in w and "126372.json" in w for w in rep.warnings), rep.warnings


def test_a_second_catalogue_of_one_heliostat_is_named_and_links_are_read_once(catalogue, tmp_path):
    root_json, _ = catalogue
    site = root_json.parent
    import shutil

    shutil.copytree(site / "AA31-heliostat-catalog", site / "AA31-copy")
    root = json.loads(root_json.read_text())
    root["links"] += [{"rel": "child", "href": "./AA31-heliostat-catalog/catalog.json"}] * 500
    root["links"].append({"rel": "child", "href": "./AA31-copy/catalog.json"})
    root_json.write_text(json.dumps(root))
    seen: list[str] = []

    def transport(href, timeout_s):
        seen.append(href)
        return open(href, "rb")

    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"], transport=transport)
    assert rep.ok and rep.heliostats == ("AA31",)
    assert sum(h.endswith("AA31-heliostat-catalog/catalog.json") for h in seen) == 1
    assert any("AA31-copy" in w and "ignored" in w for w in rep.warnings), rep.warnings


def test_a_relative_href_with_query_in_a_remote_catalogue_names_its_path(tmp_path):
    build_catalogue(tmp_path / "site")
    item = json.loads((tmp_path / "site" / _ITEM[1:]).read_text())
    item["assets"]["calibration_properties"]["href"] += "?v=1#part"
    out = tmp_path / "out"
    with _serve_hostile(tmp_path / "site", {_ITEM: (json.dumps(item).encode(), {})}) as url:
        rep = fetch_catalog(f"{url}/catalog.json", out, heliostats=["AA31"], include_tower=False)
    assert rep.ok and (out / "AA31/Calibration/126372-calibration-properties.json").is_file()


@contextlib.contextmanager
def _static_server(directory: Path, host: str, redirects: dict | None = None) -> Iterator[str]:
    """A static server of ``directory`` on ``host``; ``redirects`` maps a path to the URL
    it answers with a 302 redirect."""

    class Handler(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            if self.path in (redirects or {}):
                self.send_response(302)
                self.send_header("Location", redirects[self.path])
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            super().do_GET()

    with _http_server(functools.partial(Handler, directory=str(directory)), host) as url:
        yield url


def test_redirects_to_another_host_are_followed_unless_same_host_only(tmp_path, capsys):
    """A redirect from 127.0.0.1 to 127.0.0.2 (a CDN, a moved site) is followed; with
    --same-host-only the root is a one-line error naming the URL and the target and an
    asset a failed file. A redirect on the same host is followed either way."""
    from heliojax.paint._stac_io import _Reader

    build_catalogue(tmp_path / "site")
    with _static_server(tmp_path / "site", "127.0.0.2") as other:
        target, asset = f"{other}/catalog.json", f"{other}{_ASSET}"
        moves = {"/moved.json": target, "/here.json": "/catalog.json", _ASSET: asset}
        with _static_server(tmp_path / "site", "127.0.0.1", moves) as url:
            out = tmp_path / "o"
            argv = ["fetch", f"{url}/moved.json", "--out", str(out), "--heliostats", "AA31", "--quiet"]
            rc = _cli([*argv, "--same-host-only"])
            err = capsys.readouterr().err
            assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
            assert f"{url}/moved.json: redirects to another host, {target}: not followed" in err, err
            assert "--same-host-only" in err and not out.exists()
            rep = fetch_catalog(f"{url}/catalog.json", tmp_path / "a", heliostats=["AA31"], same_host_only=True)
            assert [f[0] for f in rep.failed] == [f"{url}{_ASSET}"], rep.failed
            assert f"download failed: redirects to another host, {asset}: not followed" in rep.failed[0][1]
            assert _cli(argv) == 0, capsys.readouterr().err
            assert (out / "AA31/Calibration/126372-calibration-properties.json").is_file()
            for same_host_only in (False, True):
                reader = _Reader(None, 5.0, 0, 1, same_host_only=same_host_only)
                with reader.chunks(f"{url}/here.json") as chunks:
                    assert json.loads(b"".join(chunks))["type"] == "Catalog"
                reader.close()


@pytest.mark.parametrize(
    ("source", "location", "refused"),
    [
        ("https://a.example/x.json", "http://a.example/x.json", "from https to plain http"),
        ("https://a.example/x.json", "file:///etc/passwd", "only http and https"),
        ("https://a.example/x.json", "https://b.example/x.json", None),
        ("http://a.example/x.json", "https://a.example/x.json", None),
        ("https://a.example/x.json", "http://[::1", "not a URL"),
        ("https://a.example/x.json", "https://a.example:99999/x.json", "not a URL"),
    ],
)
def test_a_redirect_down_to_http_or_to_another_scheme_is_refused(source, location, refused):
    """The redirect check itself (no network): https -> http and non-http targets are
    refused before they are followed; another host and an upgrade to https are not."""
    import requests

    from heliojax.paint._stac_io import RedirectRefused, _redirect_hook

    response = requests.Response()
    response.url, response.status_code, response.raw = source, 302, io.BytesIO(b"")
    response.headers["location"] = location
    check = _redirect_hook(same_host_only=False)
    if refused is None:
        assert check(response) is response
    else:
        with pytest.raises(RedirectRefused, match=refused):
            check(response)


def test_a_source_or_asset_href_that_is_no_url_is_named(catalogue, tmp_path, capsys):
    """``http://[::1`` (urllib's "Invalid IPv6 URL") as the source is a one-line error
    naming it; as an asset href that one file fails, named, and the rest is fetched."""
    root_json, _ = catalogue
    out = tmp_path / "out"
    assert _cli(["fetch", "http://[::1/catalog.json", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "http://[::1/catalog.json: not a URL" in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()
    edit_asset(root_json.parent, "AA31", "126372", "calibration_properties", href="http://[::1/x.json")
    rep = fetch_catalog(root_json, out, heliostats=["AA31"], include_tower=False)
    assert len(rep.failed) == 1 and "not a URL" in rep.failed[0][1], rep.failed
    assert (out / "AA31/Calibration/125284-calibration-properties.json").is_file()


def test_a_time_beyond_the_years_of_utc_is_named(catalogue, tmp_path, capsys):
    """An item datetime or a --start whose offset carries it past year 9999 or before
    year 1 in UTC (an OverflowError of datetime) fails that item / is a usage error."""
    root_json, _ = catalogue
    p = item_json(root_json.parent, "AA31", "126372")
    d = json.loads(p.read_text())
    d["properties"]["datetime"] = "9999-12-31T23:59:59-23:59"
    p.write_text(json.dumps(d))
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"], include_tower=False)
    assert len(rep.failed) == 1 and "outside the years 1-9999" in rep.failed[0][1], rep.failed
    assert not (tmp_path / "out/AA31/Calibration/126372-calibration-properties.json").exists()
    with pytest.raises(SystemExit):
        _cli(["fetch", str(root_json), "--out", str(tmp_path / "o"), "--start", "0001-01-01T00:00+01:00"])
    err = capsys.readouterr().err
    assert "--start" in err and "outside the years 1-9999" in err and "Traceback" not in err, err


def test_an_asset_longer_than_allowed_is_broken_off(catalogue, tmp_path, monkeypatch):
    """An asset without file:size is read to at most MAX_ASSET_BYTES (MAX_STAC_BYTES for
    JSON): a server streaming without end does not fill the disk; nothing partial is kept."""
    from heliojax.paint import _stac_io

    monkeypatch.setattr(_stac_io, "MAX_ASSET_BYTES", 100)
    root_json, _ = catalogue
    out = tmp_path / "out"
    rep = fetch_catalog(root_json, out, heliostats=["AA31"], calibration_assets=["flux_image"], include_tower=False)
    assert len(rep.failed) == 2 and all("more than 100 bytes" in f[1] for f in rep.failed), rep.failed
    assert not list(out.rglob("*.png")) and not list(out.rglob("*.part"))


def test_a_catalogue_with_a_byte_order_mark_reads(catalogue, tmp_path):
    """A STAC file saved with a UTF-8 byte-order mark (an editor's) is read."""
    root_json, _ = catalogue
    root_json.write_bytes(b"\xef\xbb\xbf" + root_json.read_bytes())
    rep = fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"], include_tower=False)
    assert rep.ok and rep.downloaded, rep


def test_a_heliostat_id_with_a_final_newline_is_no_folder_name(catalogue, tmp_path):
    """``AA31\\n-heliostat-catalog`` gave the folder ``AA31\\n`` ("$" of a regular
    expression matches before a final newline): refused like any unsafe name."""
    root_json, _ = catalogue
    p = root_json.parent / "AA31-heliostat-catalog" / "catalog.json"
    p.write_text(json.dumps({**json.loads(p.read_text()), "id": "AA31\n-heliostat-catalog"}))
    with pytest.raises(DataError, match="unsafe folder name"):
        fetch_catalog(root_json, tmp_path / "out", heliostats=None, include_tower=False)
    assert not [q for q in tmp_path.rglob("*") if "\n" in q.name]


def test_ctrl_c_cancels_the_queued_downloads_and_leaves_no_temporaries(catalogue, tmp_path):
    """Ctrl-C while files download: those queued are not started, the one under way breaks
    off at its next chunk and its temporary file is removed (the pool's exit waited for
    every queued file before)."""
    import signal
    import time

    root_json, _ = catalogue
    calls: list[str] = []

    class Slow(io.RawIOBase):
        def __init__(self, f):
            self.f, self.left = f, 40

        def readable(self):
            return True

        def read(self, n=-1):
            time.sleep(0.02)
            self.left -= 1
            return self.f.read(1) if self.left > 0 else b""

        def close(self):
            self.f.close()
            super().close()

    def transport(href, timeout_s):
        f = open(href, "rb")  # noqa: SIM115 - closed by Slow
        if "/data/" not in href:
            return f
        calls.append(href)
        if len(calls) == 1:
            # to the main thread, as a terminal's Ctrl-C reaches the waiting command: a signal
            # sent to the process may land in any of its threads (JAX's, the pool's), and the
            # main thread's wait would only see it once that wait ends (a flaky test in CI)
            signal.pthread_kill(threading.main_thread().ident or 0, signal.SIGINT)
        return Slow(f)

    out = tmp_path / "out"
    # Python's own Ctrl-C handler, whatever an earlier test in this process left installed
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            fetch_catalog(
                root_json, out, calibration_assets=ALL_CAL, transport=transport, workers=1, include_tower=False
            )
    finally:
        signal.signal(signal.SIGINT, previous)
    assert len(calls) <= 2, calls
    assert not [p for p in out.rglob("*") if p.name.endswith(".part")]


def test_a_list_option_that_names_nothing_is_a_usage_error(catalogue, tmp_path, capsys):
    """``--heliostats ,,,`` fetched the tower file only and said nothing; ``all`` among
    other asset keys is all of them."""
    root_json, _ = catalogue
    with pytest.raises(SystemExit):
        _cli(["fetch", str(root_json), "--out", str(tmp_path / "o"), "--heliostats", ",,,"])
    assert "--heliostats" in capsys.readouterr().err and not (tmp_path / "o").exists()
    argv = ["fetch", str(root_json), "--out", str(tmp_path / "a"), "--heliostats", "AA31", "--assets", "all,flux_image"]
    assert _cli([*argv, "--quiet", "--no-tower"]) == 0, capsys.readouterr().err
    assert (tmp_path / "a/AA31/Calibration/125284-flux-centered.png").is_file()


def test_a_long_hostile_href_is_shown_shortened(catalogue, tmp_path):
    """An href of 5000 characters is refused with a message of a line, not of 10 kB."""
    root_json, _ = catalogue
    edit_asset(root_json.parent, "AA31", "126372", "calibration_properties", href="data/" + "a" * 5000 + "?.json")
    with pytest.raises(DataError, match="unsafe or empty file name") as info:
        fetch_catalog(root_json, tmp_path / "out", heliostats=["AA31"], include_tower=False)
    assert len(str(info.value)) < 600, len(str(info.value))
