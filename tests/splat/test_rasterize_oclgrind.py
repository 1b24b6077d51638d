"""Every splat kernel under oclgrind: no out-of-bounds access, no access against a
buffer's read/write flags, no data race (a tiny forward and backward, float32)."""

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = [
    pytest.mark.oclgrind,
    pytest.mark.skipif(shutil.which("oclgrind") is None, reason="oclgrind is not installed"),
]

SCRIPT = textwrap.dedent(
    """
    import sys, torch
    sys.path.insert(0, {repo!r})
    from tests.splat._helpers import camera, random_scene
    from clflow.splat.ops import rasterize_gaussians
    scene = [t.requires_grad_() for t in random_scene(6, seed=0, dtype=torch.float32)]
    flow = torch.ones(6, 2, requires_grad=True)
    viewmat, K = camera(20, 18, 20.0, dtype=torch.float32)
    img, alpha, depth, meta = rasterize_gaussians(*scene, viewmat, K, 20, 18, features=flow)
    (img.sum() + alpha.sum() + depth.sum()).backward()
    assert meta["num_tile_entries"] > 0 and scene[0].grad.abs().sum() > 0
    print("done")
    """
)


def test_kernels_are_clean_under_oclgrind(tmp_path: Path):
    script = tmp_path / "render.py"
    script.write_text(SCRIPT.format(repo=str(Path(__file__).parents[2])))  # tests is a package of the repository
    log = tmp_path / "oclgrind.log"
    env = dict(os.environ, CLFLOW_DEVICE="oclgrind", POCL_CACHE_DIR=str(tmp_path / "cache"))
    result = subprocess.run(
        ["oclgrind", "--data-races", "--log", str(log), sys.executable, str(script)],
        capture_output=True, text=True, env=env, timeout=600,
    )
    assert result.returncode == 0 and "done" in result.stdout, result.stderr[-2000:]
    report = log.read_text() if log.exists() else ""
    assert report.strip() == "", report[:2000]
