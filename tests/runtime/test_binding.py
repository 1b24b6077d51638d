"""Launches bound once and replayed: the same bits as launching anew, and no recording
outlives the arrays it was made for."""

from __future__ import annotations

import gc

import numpy as np
import torch

from clflow.runtime.arrays import DeviceArray
from clflow.runtime.binding import LaunchCache

SCALE = ("common/sort.cl", "count_keys")


def cube_simulator(device, flip: float = 0.0):
    """An elastic cube of 4^3 particles falling in a 12^3 grid onto a floor through its lower
    half that is there from 3 ms on (so each substep's time matters)."""
    from clflow.mpm import Grid, HalfSpace, MaterialSpec, Simulator

    axis = 0.4 + 0.05 * torch.arange(4, dtype=torch.float64)
    x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    grid = Grid((12, 12, 12), 1.0 / 11)
    material = MaterialSpec("elastic", {"youngs_modulus": 2e4, "poissons_ratio": 0.3})
    floor = HalfSpace((0.0, 0.45, 0.0), (0.0, 1.0, 0.0), "sticky", 0.0, 3e-3, float("inf"))
    return Simulator(
        x, 0.05**3, material, grid, frame_dt=2e-3, substeps=4, flip=flip, boundaries=[floor], device=device
    )


def test_a_replayed_substep_is_the_launched_one_to_the_bit(device):
    for flip in (0.0, 0.95):
        bound, launched = cube_simulator(device, flip), cube_simulator(device, flip)
        kernels = launched.kernels
        kernels.run = lambda state, out, inputs, clamped, tape=None: kernels._enqueue(
            state, out, inputs, clamped, tape or kernels.scratch
        )  # every substep launched anew
        for _ in range(12):
            bound.step()
            launched.step()
        for name in ("x", "v", "C", "F"):
            assert torch.equal(getattr(bound.state, name), getattr(launched.state, name)), (flip, name)
        assert len(bound.kernels.bound) == 2  # the state's two buffers, each way
        assert bound.time == launched.time > 0


def test_a_recording_is_dropped_with_an_array_it_was_made_for_and_keeps_its_scratch(device):
    cache = LaunchCache()
    keys = DeviceArray.of(device, torch.zeros(8, dtype=torch.int32))
    counts = DeviceArray.zeros(device, (4,), torch.int32)  # 2 keys, the total and one block's count
    scratch_rank = {"rank": DeviceArray.empty(device, (8,), torch.int32)}  # dropped below
    kernel = device.kernel(*SCALE)
    taken = []

    def block():
        counts.zero_()
        device.launch(
            kernel, 8, dict(keys=keys, n=np.int32(8), n_keys=np.int32(2), counts=counts, rank=scratch_rank["rank"])
        )
        taken.append(device.take_scratch(64))
        device.give_back_scratch(taken[-1])

    objects = lambda: (keys, counts, scratch_rank["rank"])  # noqa: E731
    first = cache.recording(device, objects(), (), block)
    assert [type(s).__name__ for s in first.steps] == ["Fill", "BoundLaunch"] and first.scratch == taken
    assert cache.recording(device, objects(), (), block) is first and len(taken) == 1
    for _ in range(3):
        device.replay(first, None)
    assert counts.read().tolist() == [8, 0, 0, 8]  # zeroed before each count: one run's counts
    assert device.take_scratch(64) is not taken[0]  # the recording's for good
    del scratch_rank["rank"]
    gc.collect()
    assert len(cache) == 0
