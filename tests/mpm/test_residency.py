"""The simulator's state stays on the device: substeps copy nothing between host and device,
in the bridge's copy mode (what a discrete GPU does) as on shared memory."""

import dataclasses
import re

import pytest
import torch

from clflow.errors import InputError
from clflow.mpm import Force, Region, autograd
from clflow.mpm.autograd import memory_estimate, simulate
from clflow.runtime.arrays import DeviceArray
from tests.mpm._helpers import MATERIAL_CASES, random_scene

FORCE = Force(Region.box((0.3, 0.3, 0.3), (0.5, 0.7, 0.7)), start=0.0, end=0.015, acceleration=(2.0, 0.0, 0.0))


def scene(**kwargs):
    """Every material, a driver force stage that ends within the second frame (a new set of
    active stages mid-run), float64."""
    return random_scene(MATERIAL_CASES, n=400, forces=[FORCE], **kwargs)


def test_substeps_copy_nothing_in_copy_mode(copy_mode):
    sim = scene()
    assert not sim.device.zero_copy
    sim.advance_frame()  # uploads the driver accelerations of the first set of active stages
    mark = sim.device.transfers.mark()
    for _ in range(2 * sim.substeps):  # through the stage's end: the second table is uploaded once
        sim.step()
    stages_off = sim.device.transfers.since(mark)
    assert stages_off.to_host == 0 and stages_off.to_device == sim.accelerations.at(1.0).nbytes
    mark = sim.device.transfers.mark()
    for _ in range(sim.substeps):
        sim.step()
    assert sim.device.transfers.since(mark).total == 0


def test_host_edits_of_the_state_reach_the_device(copy_mode):
    sim = scene()
    sim.state.v.zero_()  # edited in place through the host view
    sim.step()
    moved = float((sim.state.x - scene().state.x).abs().max())
    assert moved < 2 * 9.81 * sim.dt**2  # started at rest: gravity's reach in one substep (not 0.6 m/s x dt)


def differentiable_run_copies(substeps: int) -> tuple[int, int]:
    """(bytes to the device, bytes to the host) of a differentiable run of 3 frames and its
    backward, at ``substeps`` substeps per frame."""
    sim = scene(substeps=substeps)
    E = torch.tensor(1e4, dtype=torch.float64, requires_grad=True)
    mark = sim.device.transfers.mark()
    frames = simulate(sim, 3, params={"youngs_modulus": E})
    (frames.x[-1].sum() + frames.v.sum()).backward()
    moved = sim.device.transfers.since(mark)
    return moved.to_device, moved.to_host


def test_a_differentiable_run_copies_per_frame_not_per_substep(copy_mode):
    """The bytes a run and its adjoint copy do not depend on the substeps per frame: each
    frame's outputs go to the host once, each frame's output gradients come back once."""
    assert differentiable_run_copies(10) == differentiable_run_copies(20)


def test_a_discrete_devices_memory_bounds_the_replay(copy_mode, monkeypatch):
    """With separate device memory and no memory_budget, backward replays frames in segments
    that fit the device (here one made small), and refuses, naming the device, a run that
    does not fit even one substep at a time."""
    sim = scene()
    need = memory_estimate(sim.n, sim.grid.nodes, 3, sim.substeps, sim.dtype, segment=3)
    small = dataclasses.replace(sim.device.info, global_mem_size=int(need / autograd.DEVICE_MEMORY_SHARE) + 1)
    monkeypatch.setattr(sim.device, "info", small)
    assert autograd._Run(sim, 3, sim.substeps).segment == 3
    with pytest.raises(InputError, match=f"{re.escape(small.label)}'s memory .* is too small for 30 frames"):
        autograd._Run(sim, 30, sim.substeps)


def test_on_shared_memory_nothing_is_copied_at_all(device):
    """A zero-copy device (PoCL outside copy mode): a whole run and its adjoint copy 0 bytes."""
    if not device.zero_copy:
        pytest.skip(f"{device.info.label} has its own memory here")
    assert differentiable_run_copies(10) == (0, 0)


def test_particle_arrays_are_both_states_and_every_per_particle_array(device):
    """What bench mpm counts per particle: one entry per particle in each, both states
    whichever is current after a substep, nothing twice."""
    from clflow.runtime.arrays import arrays_of

    sim = scene()
    for _ in range(2):
        arrays = sim.particle_arrays()
        assert all(a.shape[0] == sim.n for a in arrays)
        assert len({id(a) for a in arrays}) == len(arrays)
        assert {id(a) for a in arrays_of(sim.device_state)} < {id(a) for a in arrays}
        sim.step()


def test_a_runs_states_are_its_frames_on_the_device_and_stay_in_this_process(device):
    """Frames.states: each frame's state on the device, the same values as x, v, F; a pickled
    copy (a Ray task's) keeps x, v, F and leaves the device memory behind."""
    import pickle

    sim = scene()
    frames = simulate(sim, 2)
    assert frames.states is not None and len(frames.states) == 3
    for t, state in enumerate(frames.states):
        assert torch.equal(state.x.read(), frames.x[t]) and torch.equal(state.F.read(), frames.F[t])
    copy = pickle.loads(pickle.dumps(frames))
    assert copy.states is None and torch.equal(copy.x, frames.x) and frames.states is not None


class _LastPositions:
    """A reader of a run's frames on the device (simulate's ``reader``): its last frame's x,
    read to the host; that frame's x gradient handed back on the device."""

    def forward(self, states):
        self.frames = len(states) - 1
        return (states[-1].x.read(),)

    def backward(self, grads):
        (grad,) = grads
        device = self.device

        def state_grads(frame):
            return (DeviceArray.of(device, grad.contiguous()), None) if frame == self.frames else (None, None)

        return state_grads


def reader_run(sim, frames: int):
    """(Frames, its reader's tensors, bytes to the host) of a run with a _LastPositions reader
    and its backward."""
    E = torch.tensor(1e4, dtype=torch.float64, requires_grad=True)
    reader = _LastPositions()
    reader.device = sim.device
    mark = sim.device.transfers.mark()
    out, (last,) = simulate(sim, frames, params={"youngs_modulus": E}, reader=reader)
    last.sum().backward()
    return out, last, E.grad, sim.device.transfers.since(mark).to_host


def test_a_run_with_a_reader_reads_its_health_not_its_frames(copy_mode):
    """With a reader, a frame more costs the host only its health check (HEALTH_GROUPS pairs
    of reals), not the frame's x, v, F; the Frames read those from the device when asked,
    equal to a run's without a reader, and the gradient is the same (to rounding: the atomic
    P2G's order of addition is not fixed)."""
    from clflow.mpm.constants import HEALTH_GROUPS

    _, _, _, three = reader_run(scene(), 3)
    out, last, grad, six = reader_run(scene(), 6)
    assert six - three == 3 * HEALTH_GROUPS * 2 * 8  # float64
    E = torch.tensor(1e4, dtype=torch.float64, requires_grad=True)
    plain = simulate(scene(), 6, params={"youngs_modulus": E})
    plain.x[-1].sum().backward()
    assert torch.equal(out.x[-1], last)  # the reader's frame, read again
    close = lambda a, b: torch.allclose(a, b, rtol=1e-9, atol=1e-12)  # noqa: E731
    assert close(last, plain.x[-1]) and close(grad, E.grad)
    assert close(out.x, plain.x) and close(out.v, plain.v) and close(out.F, plain.F)
