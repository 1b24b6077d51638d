#!/usr/bin/env bash
# Wheels for a GPU machine without internet (docs/gpu.md): clflow's own and the packages a
# CUDA image with torch, numpy, scipy, opencv and matplotlib lacks, for that machine's
# Python (default 3.12) on x86-64 Linux. About 45 MB.
#
#   bash scripts/gpu_wheels.sh [DIR] [PYTHON_VERSION]      # default .whl 3.12
set -euo pipefail
cd "$(dirname "$0")/.."
dir=${1:-.whl}
py=${2:-3.12}
mkdir -p "$dir"
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux1_x86_64; do
    platforms+=(--platform "$p")
done
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$py" --implementation cp \
    "${platforms[@]}" -d "$dir" pyopencl pytools platformdirs siphash24 kornia kornia_rs av
python3 -m pip wheel -q --no-deps -w "$dir" .
ls -l "$dir"
