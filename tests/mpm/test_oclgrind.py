"""Every MPM kernel under oclgrind: no out-of-bounds access, no data race (tiny scene)."""

import os
import shutil
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import warnings
    import torch
    from clflow.mpm import Box, Force, Grid, HalfSpace, MaterialSpec, RotatingCylinder, Simulator
    warnings.simplefilter("ignore")
    gen = torch.Generator().manual_seed(0)
    x = 0.3 + 0.4 * torch.rand(20, 3, generator=gen, dtype=torch.float64)
    x[0] = torch.tensor([0.855, 0.5, 0.5], dtype=torch.float64)  # leaves the grid: clamped
    v = torch.randn(20, 3, generator=gen, dtype=torch.float64)
    v[0] = torch.tensor([30.0, 0.0, 0.0])
    names = ["elastic", "plasticine", "metal", "foam", "sand", "newtonian", "non_newtonian", "snow"]
    specs = [MaterialSpec(m) for m in names] + [MaterialSpec("sand", model="volume_corrected")]
    scenes = [(specs, torch.arange(20) % len(specs)), ([MaterialSpec("elastic")], None)]
    for specs, index in scenes:
        sim = Simulator(x, 1e-5, specs, Grid((8, 8, 8), 1 / 7), material_index=index, velocities=v, walls=None,
                        frame_dt=2e-4, substeps=2, p2g="private",
                        forces=[Force(torch.ones(20, dtype=torch.bool), 0, 1, force=(1, 0, 0))],
                        boundaries=[HalfSpace((0, 0.2, 0), (0, 1, 0), "slip", 0.3), Box((0.4,) * 3, (0.5,) * 3),
                                    RotatingCylinder((0.5,) * 3, (0, 1, 0), 0.2, 0.1, 2.0)])
        assert sim.run(1).clamped[1] == 1
    print("done on", sim.device.info.label)
    """
)


@pytest.mark.oclgrind
@pytest.mark.slow
@pytest.mark.skipif(shutil.which("oclgrind") is None, reason="oclgrind not installed")
def test_kernels_are_clean_under_oclgrind(tmp_path):
    log = tmp_path / "oclgrind.log"
    env = {**os.environ, "CLFLOW_DEVICE": "oclgrind", "POCL_CACHE_DIR": str(tmp_path / "cache")}
    res = subprocess.run(["oclgrind", "--data-races", "--log", str(log), sys.executable, "-c", SCRIPT],
                         capture_output=True, text=True, env=env, timeout=900)
    assert res.returncode == 0 and "done on Oclgrind" in res.stdout, res.stdout[-500:] + res.stderr[-2000:]
    report = log.read_text() if log.exists() else ""
    assert report.strip() == "", report[:3000]
