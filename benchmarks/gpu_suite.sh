#!/usr/bin/env bash
# The GPU figures of the performance issue in one run (a lent GPU has minutes, not hours):
# calibration at N = 100,000 x 100, the ray tracer (1 and 100 heliostats), aiming
# and discovery at N = 1,000. Each benchmark prints JSON into $OUT (default
# ./gpu_results), next to device.json naming the device and the library versions.
#
#     OUT=gpu_results bash benchmarks/gpu_suite.sh            # full sizes
#     SMALL=1 OUT=/tmp/g bash benchmarks/gpu_suite.sh         # a quick check on a CPU
#
# Each step has its own time limit, so one that runs long cannot take the others
# with it; a step that fails leaves its log and the rest still run.
set -u
cd "$(dirname "$0")/.."
OUT="${OUT:-gpu_results}"
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
# Benchmarks that simulate in a child process need the GPU in two processes: no
# preallocation of 75 % of its memory by the first.
export XLA_PYTHON_CLIENT_PREALLOCATE=false
PY="${PYTHON:-python3}"
if [ -n "${SMALL:-}" ]; then
  CAL_N=300 AIM_N=1000 RAYS=2000000 DISC_N=20
else
  CAL_N=100000 AIM_N=100000 RAYS=100000000 DISC_N=1000
fi

"$PY" - >"$OUT/device.json" <<'EOF'
import json, platform, subprocess
import jax, equinox, optimistix
try:
    gpu = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version", "--format=csv,noheader"],
                         capture_output=True, text=True, check=True).stdout.strip()
except Exception:
    gpu = None
print(json.dumps({"devices": [str(d) for d in jax.devices()], "nvidia_smi": gpu, "cpu": platform.processor(),
                  "jax": jax.__version__, "equinox": equinox.__version__,
                  "optimistix": getattr(optimistix, "__version__", "?"), "python": platform.python_version()}))
EOF
cat "$OUT/device.json"
# Fail fast (device minutes are scarce): a small fleet fit must work before anything big runs.
timeout 120 "$PY" - <<'EOF' || { echo "smoke check failed: nothing else run"; exit 1; }
import jax
jax.config.update("jax_enable_x64", True)
import heliojax as hj
from heliojax.discovery import simulate_fleet
fleet, truth = simulate_fleet(0, 8, 30, base="actuator", noise_mrad=0.2)
res = hj.fit(hj.nominal_model("actuator"), fleet)
print("smoke", type(fleet).__name__, type(res).__name__, jax.devices())
EOF

step() {  # step NAME LIMIT_S COMMAND...
  local name=$1 limit=$2
  shift 2
  local t0=$SECONDS
  timeout "$limit" "$@" >"$OUT/$name.json" 2>"$OUT/$name.log"
  local rc=$?
  echo "== $name rc=$rc wall=$((SECONDS - t0)) s"
  tail -c 1500 "$OUT/$name.json"
  echo
  [ "$rc" = 0 ] || tail -n 15 "$OUT/$name.log"
}

# STEPS picks what runs (a lent GPU runs one command for at most 10 minutes: split the
# suite over two calls on the warm machine, e.g. STEPS="calibration aim raytrace", then
# STEPS=discovery).
STEPS="${STEPS:-calibration aim raytrace discovery}"
wants() { [[ " $STEPS " == *" $1 "* ]]; }

# Which LM linear solve suits the device, at a hundredth of the size (H200, 1,000 x 100:
# QR 1.22 s, Cholesky 0.039 s; see the README), then the full size with the library's
# default step (Cholesky on GPUs), plain vmap against the straggler restart (the GPU
# default), and a profile of one more warm call of the default.
CAL_DATA="${CAL_DATA:-${TMPDIR:-/tmp}/heliojax_cal_${CAL_N}.npz}"
if wants calibration; then
  step calibration_choice "${CHOICE_LIMIT:-120}" "$PY" benchmarks/calibration_speed.py \
    --heliostats "$((CAL_N / 100))" --records 100 --skip-scipy --skip-robust --skip-other-bucket --repeats 2 \
    --strategy vmap --linear-solver qr,cholesky --json
  step calibration "${CAL_LIMIT:-200}" "$PY" benchmarks/calibration_speed.py \
    --heliostats "$CAL_N" --records 100 --skip-scipy --skip-robust --skip-other-bucket --repeats 2 \
    --strategy "${CAL_STRATEGY:-vmap-restart,vmap}" --linear-solver "${CAL_SOLVER:-auto}" --data "$CAL_DATA" --json
  step calibration_profile "${CAL_LIMIT:-200}" "$PY" benchmarks/calibration_speed.py \
    --heliostats "$CAL_N" --records 100 --skip-scipy --skip-robust --skip-other-bucket --repeats 1 \
    --strategy vmap-restart --data "$CAL_DATA" --profile "${TMPDIR:-/tmp}/heliojax_profile" --json
fi
if wants aim; then
  step aim "${AIM_LIMIT:-60}" "$PY" benchmarks/aim_speed.py --heliostats "$AIM_N" --instants 48
fi
if wants raytrace; then
  step raytrace "${RAY_LIMIT:-60}" "$PY" benchmarks/raytrace_speed.py --rays "$RAYS" --json
fi
if wants discovery; then
  step discovery "${DISC_LIMIT:-240}" "$PY" benchmarks/discovery.py \
    --heliostats "$DISC_N" --records 60 --seeds 1 --scenarios backlash --log-level INFO
fi
