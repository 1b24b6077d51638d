"""The device suites again as a discrete GPU runs them: the bridge's copy mode (separate
device buffers, explicit copies), the GPU plan's kernel shapes (work-group scans and sorts,
the cell-sorted gather P2G and adjoint, the rasteriser's work-group per tile) and the atomic
P2G path, none of which a CPU device would otherwise take. A bug of that class (a host write
the device never sees, an atomic sum onto a stale grid, a barrier or local-memory slip in a
work-group kernel) fails here, on PoCL, in CI."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# The copy mode in the CPU plan runs the suites whose kernels' buffers differ between the plans
# (the private P2G copies and the SIMD lanes); the rasteriser's and the flow's host side in copy
# mode is the same in either plan, and copy+gpu-kernels runs it. The atomic P2G mode leaves out
# the files that run every P2G path by name (so the copy modes run the atomic one there) and the
# adjoint substep's, whose kernels are the CPU plan's whichever path the forward took (its
# test_the_adjoint_takes_the_p2g_path_taken).
SAME_IN_THE_ATOMIC_MODE = [
    "tests/mpm/test_substep.py",
    "tests/mpm/test_population.py",
    "tests/mpm/test_adjoint_substep.py",
]
MODES = {
    "copy": ({"CLFLOW_BRIDGE": "copy"}, ["tests/mpm", "tests/runtime"]),
    "copy+atomic-p2g": (
        {"CLFLOW_BRIDGE": "copy", "CLFLOW_P2G": "atomic"},
        ["tests/mpm", *(f"--ignore={path}" for path in SAME_IN_THE_ATOMIC_MODE)],
    ),
    "copy+gpu-kernels": (
        {"CLFLOW_BRIDGE": "copy", "CLFLOW_KERNELS": "gpu"},
        ["tests/mpm", "tests/splat", "tests/flow", "tests/runtime"],
    ),
}


@pytest.mark.slow
@pytest.mark.parametrize("mode", list(MODES))
def test_device_suites_pass_in_the_discrete_gpu_modes(mode):
    env_mode, suites = MODES[mode]
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    env.update(env_mode)
    res = subprocess.run(
        # oclgrind's tests run their own simulated device, the same in every mode
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k", "not oclgrind", *suites],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert res.returncode == 0, f"{mode}: {' '.join(suites)}\n{res.stdout[-6000:]}\n{res.stderr[-2000:]}"
