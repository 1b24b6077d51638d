#!/usr/bin/env bash
# Set up clflow on a Debian/Ubuntu machine; safe to run again (it skips what is done).
#   1. PoCL (the CPU OpenCL driver), the ICD loader and oclgrind, from apt;
#   2. a virtual environment in .venv;
#   3. torch 2.13.0 first (a CPU build; any other torch request pulls a multi-GB CUDA build),
#   4. then clflow itself (editable) with its test, video, sweep and view extras (diffusers,
#      transformers, accelerate: `clflow generate`, whose tests build tiny models; Ray: the
#      tests of `clflow sweep`; viser: `clflow view`; taichi: the peer of `clflow bench mpm --peer`;
#      no torch in any); pip brings the dependencies that
#      pyproject.toml declares (PyAV with its own FFmpeg and libx264 for H.264 video, Pillow,
#      matplotlib, ...), none of which asks for another torch.
set -euo pipefail
cd "$(dirname "$0")/.."

apt_packages=(pocl-opencl-icd ocl-icd-libopencl1 clinfo oclgrind)
# CI also opens the results page (results/index.html) in a headless browser and checks the
# kernels' formatting
[ "${CI:-}" = true ] && apt_packages+=(chromium clang-format)
if ! dpkg -s "${apt_packages[@]}" >/dev/null 2>&1; then
    sudo=""
    [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${apt_packages[@]}" >/dev/null
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
pip=(.venv/bin/python -m pip install --quiet --disable-pip-version-check)
.venv/bin/python -c 'import torch, sys; sys.exit(torch.__version__.split("+")[0] != "2.13.0")' 2>/dev/null \
    || "${pip[@]}" torch==2.13.0
"${pip[@]}" -e ".[test,video,sweep,view,peers]"
echo "clflow is set up in $(pwd)/.venv"
