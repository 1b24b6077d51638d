"""The GPU plan's kernels under oclgrind: no out-of-bounds access, no data race (the
work-group scan and radix sort with their barriers and local
memory, the counting sort's integer atomics, the cell-sorted gather P2G, G2P and G2P adjoint,
APIC and the PIC/FLIP blend)."""

import textwrap

import pytest

from tests.mpm._helpers import assert_clean_under_oclgrind

pytestmark = [pytest.mark.oclgrind, pytest.mark.slow]

SCRIPT = textwrap.dedent(
    """
    import os
    os.environ["CLFLOW_KERNELS"] = "gpu"
    import warnings
    import torch
    from clflow.mpm.autograd import simulate
    from clflow.runtime.sort import sort_by_key, sort_pairs
    from tests.mpm._helpers import MATERIAL_CASES, random_scene
    warnings.simplefilter("ignore")
    gen = torch.Generator().manual_seed(0)
    keys = torch.randint(0, 2**20, (2100,), generator=gen, dtype=torch.int32)  # two blocks of 2048
    sorted_keys, _ = sort_pairs(keys, torch.arange(2100, dtype=torch.int32), key_bits=20)
    assert torch.equal(sorted_keys, torch.sort(keys).values)
    order, _ = sort_by_key(keys % 37, 37)
    assert torch.equal(order.long(), torch.sort(keys % 37, stable=True).indices)
    for flip in (0.0, 0.9):
        sim = random_scene({"plasticine": MATERIAL_CASES["plasticine"]}, n=13, substeps=2, frame_dt=2e-4,
                           walls=None, flip=flip)
        assert sim.kernels.p2g == "gather"
        v0 = sim.state.v.clone().requires_grad_()
        (simulate(sim, 1, velocities=v0).x ** 2).sum().backward()
        assert bool(torch.isfinite(v0.grad).all()) and float(v0.grad.abs().sum()) > 0
    print("done on", sim.device.info.label)
    """
)


def test_gpu_plan_kernels_are_clean_under_oclgrind(oclgrind):
    assert_clean_under_oclgrind(oclgrind, SCRIPT)
