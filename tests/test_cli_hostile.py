"""Hostile input through the CLI, as a table of cases: each ends with a short error
(exit 2) naming the flag, file or field, no traceback and no output file written."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import heliojax as hj
from heliojax.cli._main import main


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse's own usage errors
        rc = int(e.code or 0)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def _config(tmp: Path, text: str | bytes) -> str:
    path = tmp / "config.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    return str(path)


def _a_file(tmp: Path) -> Path:
    path = tmp / "a-file"
    path.write_text("x")
    return path


def _a_dir(tmp: Path) -> Path:
    path = tmp / "a-dir"
    path.mkdir(exist_ok=True)
    return path


# (case, argv from the temporary directory, text the error must contain)
CASES = [
    ("negative seed", lambda t: ["calibrate", "--seed", "-1"], "--seed"),
    ("zero steps", lambda t: ["calibrate", "--max-steps", "0"], "--max-steps"),
    ("train fraction above 1", lambda t: ["calibrate", "--train-fraction", "1.5"], "--train-fraction"),
    ("nan learning rate", lambda t: ["reconstruct", "--learning-rate", "nan"], "--learning-rate"),
    ("zero reconstruction steps", lambda t: ["reconstruct", "--steps", "0"], "--steps"),
    ("zero pixels", lambda t: ["trace", str(t), "--heliostat", "AA39", "--pixels", "0"], "--pixels"),
    ("zero rays", lambda t: ["trace", str(t), "--heliostat", "AA39", "--rays-per-point", "0"], "--rays-per-point"),
    ("sun below the horizon", lambda t: ["trace", str(t), "--heliostat", "AA39", "--sun-elevation", "-30"], "--sun"),
    ("negative timeout", lambda t: ["fetch", "--out", str(t / "o"), "--timeout", "-1"], "--timeout"),
    ("no workers", lambda t: ["fetch", "--out", str(t / "o"), "--workers", "0"], "--workers"),
    ("alpha of 0", lambda t: ["discover", "--alpha", "0"], "--alpha"),
    (
        "config float for an int",
        lambda t: ["calibrate", "--config", _config(t, "[calibrate]\nmax_steps = 2.5\n")],
        "max_steps",
    ),
    (
        "config string for a flag",
        lambda t: ["calibrate", "--config", _config(t, '[calibrate]\nprior = "false"\n')],
        "prior",
    ),
    (
        "config number for a choice",
        lambda t: ["calibrate", "--config", _config(t, "[calibrate]\nmodel = 5\n")],
        "model",
    ),
    (
        "config unknown choice",
        lambda t: ["calibrate", "--config", _config(t, '[calibrate]\nsplit = "random"\n')],
        "split",
    ),
    ("config out of range", lambda t: ["calibrate", "--config", _config(t, "[calibrate]\nseed = -3\n")], "seed"),
    (
        "config misspelled table",
        lambda t: ["calibrate", "--config", _config(t, "[calibrat]\nquiet = true\n")],
        "calibrat",
    ),
    ("config unknown key", lambda t: ["calibrate", "--config", _config(t, "[calibrate]\nsteps = 3\n")], "steps"),
    ("config not TOML", lambda t: ["calibrate", "--config", _config(t, b"\xff\xfe\x00garbage")], "config.toml"),
    ("config missing", lambda t: ["calibrate", "--config", str(t / "nope.toml")], "nope.toml"),
    ("report is a directory", lambda t: ["calibrate", "--report", str(_a_dir(t))], "--report"),
    ("out below a file", lambda t: ["calibrate", "--out", str(_a_file(t) / "results.h5")], "--out"),
    ("plot is a directory", lambda t: ["inspect", "--plot", str(_a_dir(t))], "--plot"),
    ("figures is a file", lambda t: ["discover", "--figures", str(_a_file(t))], "--figures"),
    ("cache below a file", lambda t: ["discover", "--cache-dir", str(_a_file(t) / "c")], "--cache-dir"),
    ("trace out is a file", lambda t: ["trace", str(t), "--heliostat", "AA39", "--out", str(_a_file(t))], "--out"),
    (
        "accept report is a directory",
        lambda t: ["accept", "--results", "r.csv", "--contract", "c.toml", "--report", str(_a_dir(t))],
        "--report",
    ),
    ("data directory missing", lambda t: ["calibrate", str(t / "missing")], "missing"),
]


@pytest.mark.parametrize(("argv", "expected"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_a_short_clean_error(argv, expected, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    before = {p for p in tmp_path.rglob("*")}
    rc, _, err = _run(argv(tmp_path), capsys)
    assert rc == 2, err
    assert expected in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) <= 2, err
    assert {p for p in tmp_path.rglob("*")} - before - {tmp_path / "a-dir", tmp_path / "a-file"} <= {
        tmp_path / "config.toml"
    }


def test_inspect_survives_a_heliostat_without_usable_records(tmp_path, capsys):
    data = tmp_path / "paint"
    shutil.copytree(hj.default_data_dir(), data)
    for record in (data / "BL14" / "Calibration").iterdir():
        record.unlink()
    rc, out, err = _run(["inspect", str(data)], capsys)
    assert rc == 0, err
    assert "BE36" in out and "Traceback" not in err
