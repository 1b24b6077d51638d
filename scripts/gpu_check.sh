#!/usr/bin/env bash
# Check clflow on a GPU in one command (docs/gpu.md): the tests with the GPU selected, then
# `clflow bench mpm`, `mpm-adjoint`, `raster` and `optimize` at GPU scale, into one JSON.
#
#   bash scripts/gpu_check.sh [--wheels DIR] [gpu_check.py options: --suite all, --out FILE, ...]
#
# --wheels DIR: install the wheels in DIR first (made by scripts/gpu_wheels.sh on a machine
# with internet) into a folder on PYTHONPATH, for a GPU machine without internet. The NVIDIA,
# AMD or Intel OpenCL driver is found even without an ICD entry (clflow devices says so).
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
if [ "${1:-}" = "--wheels" ]; then
    site=${CLFLOW_WHEEL_SITE:-/tmp/clflow-site}
    "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" "$2"/*.whl
    export PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}"
    shift 2
fi
exec "$python" scripts/gpu_check.py "$@"
