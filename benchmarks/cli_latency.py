"""CLI latency as a user sees it: wall time of each ``heliojax`` command on the
embedded data, cold (a fresh, empty compilation cache directory) and warm (the
same command again with that cache), each in a new process.

Issue targets (2-core CPU): ``heliojax calibrate`` warm <= 2 s and cold <= 6 s,
``heliojax --help`` <= 1 s. Prints JSON (seconds; the median of ``--repeats``
warm runs, each cold run once per repeat with its own fresh cache).

    python benchmarks/cli_latency.py
    python benchmarks/cli_latency.py --commands calibrate,inspect --repeats 5
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

from heliojax.cli._common import integer

COMMANDS = {
    "--version": ["--version"],
    "--help": ["--help"],
    "calibrate --help": ["calibrate", "--help"],
    "inspect": ["inspect"],
    "calibrate": ["calibrate", "--quiet"],
    "calibrate --model stone8": ["calibrate", "--model", "stone8", "--quiet"],
    "discover": ["discover", "--quiet", "--report", "{out}/report.json"],
}
USES_CACHE = {"calibrate", "discover"}
BYTECODE_NOTE = (
    "By default the commands run as Python runs for a user: bytecode cached in __pycache__, as "
    "pip install writes it. With --no-bytecode they inherit PYTHONDONTWRITEBYTECODE; a process "
    "that compiles heliojax's ~60 modules from source every time takes 0.3-0.4 s longer."
)


def _run(argv: list[str], cache: str, out: str, inherit_bytecode_setting: bool) -> float:
    argv = [a.replace("{out}", out) for a in argv]
    if argv[0] in USES_CACHE:
        argv = [*argv, "--cache-dir", cache]
    env = dict(os.environ, MPLBACKEND="Agg")
    if not inherit_bytecode_setting:
        env.pop("PYTHONDONTWRITEBYTECODE", None)  # Python's default, as an installed package has it
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "heliojax.cli._main", *argv], capture_output=True, env=env, cwd=out)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"heliojax {' '.join(argv)} failed:\n{proc.stderr.decode()[-2000:]}")
    return wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--commands",
        default="--version,--help,calibrate --help,inspect,calibrate,calibrate --model stone8",
        help=f"comma-separated, from: {', '.join(COMMANDS)}",
    )
    ap.add_argument("--repeats", type=integer(1), default=3)
    ap.add_argument("--no-bytecode", action="store_true", help=BYTECODE_NOTE)
    args = ap.parse_args()
    names = [c.strip() for c in args.commands.split(",") if c.strip()]
    unknown = sorted(set(names) - set(COMMANDS))
    if unknown:
        raise SystemExit(f"unknown commands {unknown}; known: {sorted(COMMANDS)}")
    results = {}
    for name in names:
        cold, warm = [], []
        for _ in range(args.repeats):
            work = tempfile.mkdtemp(prefix="heliojax-cli-latency-")
            try:
                cache = os.path.join(work, "cache")
                cold.append(_run(COMMANDS[name], cache, work, args.no_bytecode))
                warm.append(_run(COMMANDS[name], cache, work, args.no_bytecode))
            finally:
                shutil.rmtree(work, ignore_errors=True)
        results[name] = {
            "cold_s": round(statistics.median(cold), 3),
            "warm_s": round(statistics.median(warm), 3),
            "cold_runs_s": [round(x, 3) for x in cold],
            "warm_runs_s": [round(x, 3) for x in warm],
        }
    print(
        json.dumps(
            {
                "benchmark": "cli_latency",
                "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
                "load_average_1min": round(os.getloadavg()[0], 2),
                "repeats": args.repeats,
                "python_bytecode_cached": not (args.no_bytecode and os.environ.get("PYTHONDONTWRITEBYTECODE")),
                # every command imports these through jax; ml_dtypes 0.7.0 alone took 0.55 s (pyproject.toml)
                "versions": {n: importlib.metadata.version(n) for n in ("jax", "jaxlib", "ml_dtypes", "numpy")},
                "commands": results,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
