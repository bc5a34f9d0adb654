"""What a new user's walk through the README ran into (2026-12-08), each fixed.

Covered here: ``fetch`` without a network printed a 400-character
``ConnectionError(MaxRetryError(... NameResolutionError(...)))`` repr; ``trace
--heliostat AA39`` (the help's example, a heliostat the embedded data lack) named the
missing properties file but not the heliostats there are; ``calibrate --records``
printed its warning about heliostats without a held-out record twice; ``aim`` of a
``results.h5`` that does not exist said "no such file" without saying that ``calibrate``
writes one only with ``--out``.

Covered where the behaviour lives: ``plan --before`` with ``--records-out`` gave the
fit's training records after the cut the role ``train``
(``tests/test_cli_hostile.py::test_plan_among_existing_records_offers_none_the_fit_used``);
``plan`` long after the fit said nothing (``tests/test_hostile_round9.py``); the closing
"Named:" line of discovery's Markdown read flagged names as certain
(``tests/test_discovery.py``); a ``+nn`` run's training RMS covered records before a
change point (``tests/test_cli_hostile.py``); ``accept`` printed FAIL without the reason
(``tests/test_acceptance_io.py``); the held-out comparison with the uncalibrated model
(``tests/test_loo.py``).
"""

from __future__ import annotations

import csv
import socket

import requests
import urllib3
from helpers import run_cli

import heliojax as hj
from heliojax.paint._stac_io import read_failure


def test_a_failed_connection_is_one_readable_line():
    resolve = urllib3.exceptions.NameResolutionError(
        "paint-database.org",
        "HTTPSConnection(host='paint-database.org', port=443)",  # pyright: ignore[reportArgumentType]
        socket.gaierror(-2, "Name or service not known"),
    )
    retried = urllib3.exceptions.MaxRetryError(None, "/WRI1030197/catalog.json", resolve)  # pyright: ignore[reportArgumentType]
    text = read_failure(requests.exceptions.ConnectionError(retried))
    assert text.startswith("cannot reach the server (Failed to resolve 'paint-database.org'"), text
    assert "no network connection" in text
    assert "MaxRetryError" not in text and "HTTPSConnection(" not in text and len(text) < 200, text
    # another failure: its type and message, shortened
    assert read_failure(TimeoutError("read timed out")) == "TimeoutError: read timed out"
    long = read_failure(OSError("x" * 5000))
    assert long.startswith("OSError: ") and len(long) < 260


def test_trace_of_a_heliostat_the_data_lack_names_those_there_are(tmp_path, capsys):
    argv = ["trace", "--heliostat", "AA39", "--sun-azimuth", "-20", "--sun-elevation", "35"]
    rc, _, err = run_cli([*argv, "--out", str(tmp_path / "t"), "--quiet"], capsys)
    assert rc == 2, err
    assert "--heliostat AA39: no AA39/Properties/AA39-heliostat-properties.json" in err, err
    assert "its heliostats: BE36, BF56, BG23, BH20, BL14" in err, err
    assert not (tmp_path / "t").exists()


def test_a_missing_results_file_says_that_calibrate_writes_one(tmp_path, capsys):
    missing = tmp_path / "out" / "results.h5"
    rc, _, err = run_cli(["aim", str(missing), "--time", "2023-06-21T12:00"], capsys)
    assert rc == 2 and "no such file (heliojax calibrate writes one with --out" in err, err
    # a file of another kind gets no such hint (accept's --results is a CSV or summary.json)
    rc, _, err = run_cli(["accept", "--results", str(tmp_path / "f.csv"), "--contract", str(tmp_path / "c")], capsys)
    assert rc == 2 and "calibrate writes" not in err, err


def test_the_records_warning_is_given_once(tmp_path, capsys):
    """BE36 trains on some records and gets no test role while BF56 gets test roles:
    the warning that BE36 is evaluated on nothing came twice (the command's own check
    of the file, then the calibration)."""
    fleet = hj.load_paint_directory(hj.default_data_dir())
    rows = []
    for name, roles in (("BE36", ("train",) * 20), ("BF56", ("train",) * 20 + ("test",) * 10)):
        h = fleet.index(name)
        ids = [int(r) for r, m in zip(fleet.record_id[h], fleet.mask[h], strict=True) if m]
        rows += [(name, rid, role) for rid, role in zip(ids, roles, strict=False)]
    records = tmp_path / "records.csv"
    with records.open("w", newline="") as f:
        csv.writer(f).writerows([("heliostat_id", "record_id", "role"), *rows])
    argv = ["calibrate", "--records", str(records), "--model", "stone8", "--max-steps", "3", "--no-robust"]
    rc, _, err = run_cli([*argv, "--cache-dir", "none", "--quiet"], capsys)
    assert rc == 0, err
    assert err.count("train but get no held-out record") == 1 and "BE36 (" in err, err
