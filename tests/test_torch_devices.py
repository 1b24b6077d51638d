"""Tensors on any torch device: results and gradients come back on the inputs' device,
copied through the host once per call and counted (needs torch with CUDA to run the real
round trip; the rules that need no GPU run everywhere)."""

import pytest
import torch

from clflow.errors import InputError
from clflow.runtime.arrays import origin_device

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="torch has no CUDA device here")


def test_inputs_on_different_devices_are_refused_in_one_line():
    with pytest.raises(InputError, match=r"different torch devices \(cpu, meta\)"):
        origin_device(torch.zeros(1), None, torch.zeros(1, device="meta"), what="the tensors")
    assert origin_device(None, 3.0) == torch.device("cpu")


@cuda
def test_rasterize_takes_and_returns_cuda_tensors(device):
    from clflow.splat.ops import rasterize_gaussians

    g = torch.Generator().manual_seed(0)
    n = 200
    means = (torch.rand(n, 3, generator=g) - 0.5 + torch.tensor([0.0, 0.0, 3.0])).cuda().requires_grad_()
    quats, scales = torch.randn(n, 4, generator=g).cuda(), torch.full((n, 3), 0.02).cuda()
    opacities, colors = torch.full((n,), 0.5).cuda(), torch.rand(n, 3, generator=g).cuda()
    K = torch.tensor([[64.0, 0, 32], [0, 64, 32], [0, 0, 1]]).cuda()
    mark = device.transfers.mark()
    image, alpha, depth, meta = rasterize_gaussians(
        means, quats, scales, opacities, colors, torch.eye(4).cuda(), K, 64, 64
    )
    assert image.device.type == "cuda" and meta["radii"].device.type == "cuda"
    image.sum().backward()
    assert means.grad is not None and means.grad.device.type == "cuda"
    moved = device.transfers.since(mark)
    assert moved.to_host >= means.numel() * 4 and moved.to_device >= image.numel() * 4
    cpu = rasterize_gaussians(*(t.detach().cpu() for t in (means, quats, scales, opacities, colors)),
                              torch.eye(4), K.cpu(), 64, 64)[0]  # fmt: skip
    assert torch.equal(image.detach().cpu(), cpu)


@cuda
def test_simulate_takes_and_returns_cuda_tensors():
    from clflow.mpm import Grid, MaterialSpec, Simulator
    from clflow.mpm.autograd import simulate
    from tests.mpm._helpers import cube

    sim = Simulator(cube(4, 0.4, 0.6), 1e-5, MaterialSpec("elastic", {"youngs_modulus": 1e4}), Grid((16,) * 3, 1 / 16))
    E = torch.tensor(1e4, dtype=torch.float64, device="cuda", requires_grad=True)
    frames = simulate(sim, 2, params={"youngs_modulus": E})
    assert frames.x.device.type == "cuda"
    frames.x[-1].sum().backward()
    assert E.grad is not None and E.grad.device.type == "cuda" and bool(torch.isfinite(E.grad))
