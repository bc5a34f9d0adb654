"""Execute notebooks/planning.ipynb (stored without outputs) with nbclient: aiming
the embedded fleet for a day, a plan for the next measurements, and the
retrospective check on the embedded heliostats with at least 40 records."""

import re

from _notebooks import run_notebook


def test_notebook_planning_runs(tmp_path, monkeypatch):
    # the operating envelope from every 60th day of the year instead of every 15th (as
    # the plan command's tests): the plan's cost weights, not what is asserted below
    _, text, n_images = run_notebook("planning.ipynb", tmp_path, monkeypatch, overrides={"ENVELOPE_DAY_STEP": 60})
    usable, total = map(int, re.search(r"(\d+) of (\d+) commands usable", text).groups())
    assert 0 < usable < total  # night and out-of-range commands are flagged
    plans = re.findall(r"(\w+): ([0-9.]+) -> ([0-9.]+) mrad;", text)
    assert len(plans) == 5 and all(float(after) < float(before) for _, before, after in plans)
    checks = re.findall(r"planner ([0-9.]+) mrad, first in time ([0-9.]+) mrad", text)
    assert len(checks) == 3  # BE36, BF56, BG23 have >= 40 records
    assert all(0.0 < float(p) < 50.0 and 0.0 < float(f) < 50.0 for p, f in checks)
    assert n_images == 3
