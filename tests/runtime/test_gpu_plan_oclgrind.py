"""The GPU plan's kernels under oclgrind: no out-of-bounds access, no data race (the
work-group scan in its two-launch form, and in one over block sums counted with the keys,
and radix sort with their barriers and local memory, the counting sort's integer atomics,
the stress kernels that key the particles by cell, the cell-sorted gather P2G over blocks
with its local memory and barriers, G2P and G2P adjoint, APIC and the PIC/FLIP blend)."""

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
    from clflow.runtime import get_device
    from clflow.runtime.arrays import DeviceArray
    from clflow.runtime.sort import scan_exclusive, sort_by_key, sort_pairs
    from tests.mpm._helpers import MATERIAL_CASES, assert_velocity_gradient, random_scene, tiny_plasticine
    warnings.simplefilter("ignore")
    gen = torch.Generator().manual_seed(0)
    keys = torch.randint(0, 2**20, (2100,), generator=gen, dtype=torch.int32)  # two blocks of 2048
    sorted_keys, _ = sort_pairs(keys, torch.arange(2100, dtype=torch.int32), key_bits=20)
    assert torch.equal(sorted_keys, torch.sort(keys).values)
    for n_keys in (37, 5000):  # one block of keys; three, whose counts the keys counted
        order, _ = sort_by_key(keys % n_keys, n_keys)
        assert torch.equal(order.long(), torch.sort(keys % n_keys, stable=True).indices)
    counts = torch.randint(0, 9, (5000,), generator=gen, dtype=torch.int32)  # three blocks: the two-launch scan
    device = get_device()
    scanned = DeviceArray.of(device, torch.zeros(5001, dtype=torch.int32))
    scan_exclusive(device, DeviceArray.of(device, counts), scanned, 5000)
    assert torch.equal(scanned.read()[1:], torch.cumsum(counts, 0).to(torch.int32))
    for flip in (0.0, 0.9):
        sim = tiny_plasticine(flip=flip)
        assert sim.kernels.p2g == "gather"
        assert_velocity_gradient(sim)
    elastic = {"elastic": MATERIAL_CASES["elastic"]}  # the fused elastic stress that keys the cells
    assert_velocity_gradient(random_scene(elastic, n=13, substeps=2, frame_dt=2e-4, walls=None))
    print("done on", sim.device.info.label)
    """
)


def test_gpu_plan_kernels_are_clean_under_oclgrind(oclgrind):
    assert_clean_under_oclgrind(oclgrind, SCRIPT)
