"""The GPU plan's kernels are GPU-shaped, checked without a GPU.

In the bridge's copy mode with the GPU plan forced (CLFLOW_KERNELS=gpu), every launch of a
262k-particle substep, of its adjoint and of a 100k-Gaussian rasteriser call is recorded;
a launch fails the test when one work-item is given more than MAX_ELEMENTS_PER_WORK_ITEM
elements of its largest buffer (a one-work-item scan, a sort over 64 blocks, private grid
copies: the CPU shapes that took 77-88 % of an H200's time), and a substep when it makes
more launches than the design below. The profile of a real GPU (clflow bench --profile)
says the rest.
"""

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

MAX_ELEMENTS_PER_WORK_ITEM = 256
# bytes of local memory a work-group may take: NVIDIA's OpenCL gives one 48 KiB (the scans and
# sorts take a fixed 26 KiB or less, within the 32 KiB of any full-profile device; the
# compositing kernels size their batches to the device's, up to this)
MAX_LOCAL_MEMORY = 48 * 1024
# The GPU plan's forward substep: the stress (the SVD inline) with the particles keyed and
# counted by cell, the counts' scan (one launch up to 4 M cells: the keys counted its block
# sums), place_keys, p2g_blocks (each cell's run in index order, the blocks' tiles of sums),
# p2g_blocks_update (the tiles' sums and the grid update), g2p_sorted.
SUBSTEP_LAUNCHES = {"elastic": 6, "sand": 6}
# Its adjoint, over the forward's cell sort kept in the tape: g2p_adjoint_records,
# g2p_adjoint_gather_update (the gather and the grid update's adjoint), p2g_adjoint, [SVD],
# stress adjoint.
ADJOINT_LAUNCHES = {"elastic": 4, "sand": 5}
ITEMSIZE = {"char": 1, "uchar": 1, "short": 2, "ushort": 2, "int": 4, "uint": 4, "float": 4, "double": 8}


@dataclass
class Launch:
    kernel: str
    work_items: int
    elements: int  # of the launch's largest buffer argument
    local_memory: int  # bytes of local memory a work-group takes (the driver's count)

    @property
    def per_work_item(self) -> float:
        return self.elements / self.work_items


def buffer_elements(value, type_name: str, real: str) -> int:
    buffer = getattr(value, "buffer", value)  # a DeviceArray, or a pyopencl Buffer
    base = type_name.rstrip("*").split()[-1]
    return buffer.size // ITEMSIZE[real if base == "real" else base]


@pytest.fixture
def launches(device, monkeypatch, copy_mode):
    """The GPU plan in copy mode; returns the list every Device.launch is appended to."""
    import pyopencl as cl

    monkeypatch.setenv("CLFLOW_KERNELS", "gpu")
    recorded: list[Launch] = []
    launch = device.launch

    def recording(kernel, global_size, args, local_size=64):
        signature = device.signature(kernel)
        pointers = [a for a in signature.arguments if a.type_name.endswith("*")]
        elements = max((buffer_elements(args[a.name], a.type_name, signature.real) for a in pointers), default=0)
        work_items = math.prod([global_size] if isinstance(global_size, int) else global_size)
        local_memory = kernel.get_work_group_info(cl.kernel_work_group_info.LOCAL_MEM_SIZE, device.cl_device)
        recorded.append(Launch(kernel.function_name, work_items, elements, local_memory))
        return launch(kernel, global_size, args, local_size)

    monkeypatch.setattr(device, "launch", recording)
    return recorded


def assert_gpu_shaped(recorded: list[Launch]) -> None:
    walkers = [f"{x.kernel}: {x.elements:,} elements on {x.work_items:,} work-items" for x in recorded]
    too_long = [w for w, x in zip(walkers, recorded) if x.per_work_item > MAX_ELEMENTS_PER_WORK_ITEM]
    assert not too_long, "CPU-shaped launches in the GPU plan:\n" + "\n".join(too_long)
    greedy = {x.kernel: x.local_memory for x in recorded if x.local_memory > MAX_LOCAL_MEMORY}
    assert not greedy, f"work-groups over {MAX_LOCAL_MEMORY} B of local memory: {greedy}"


def cube_simulator(device, material: str):
    """bench mpm's scene: 64^3 = 262,144 particles, 2 per cell and axis, in a 64^3 grid."""
    from clflow.mpm import Grid, MaterialSpec, Simulator

    h = 0.5 / 64  # a cube of side 0.5 m
    axis = 0.25 + h * (0.5 + torch.arange(64, dtype=torch.float64))
    x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return Simulator(x, h**3, MaterialSpec(material), Grid((64,) * 3, 1 / 64), frame_dt=1e-3, device=device)


@pytest.mark.slow
@pytest.mark.parametrize("material", ["elastic", "sand"])
def test_a_262k_substep_and_its_adjoint_are_gpu_shaped(device, launches, material):
    from clflow.mpm.adjoint import StateGrad, SubstepAdjoint
    from clflow.runtime.arrays import DeviceArray

    sim = cube_simulator(device, material)
    assert sim.kernels.p2g == "gather"
    sim.step()
    launches.clear()
    state = sim.device_state  # a substep's launches as it binds them (a replay launches the same)
    sim.kernels.record(
        state, state.empty_like(), sim.substep_inputs(), DeviceArray.zeros(device, (sim.n,), torch.uint8)
    )
    forward = list(launches)
    assert_gpu_shaped(forward)
    assert len(forward) == SUBSTEP_LAUNCHES[material], [x.kernel for x in forward]
    assert not {"p2g_private", "scan_serial", "radix_histogram", "radix_scatter"} & {x.kernel for x in forward}
    assert not [x.kernel for x in forward if x.kernel.endswith("_simd")]  # the PoCL-made SIMD-lane stress kernels

    n, dtype = sim.n, sim.dtype
    tape = sim.kernels.empty_tape()
    state, inputs = sim.device_state, sim.substep_inputs()
    after = state.empty_like()
    sim.kernels.run(state, after, inputs, DeviceArray.zeros(device, (n,), torch.uint8), tape=tape)
    adjoint = SubstepAdjoint(device, dtype, n, sim.grid, sim.particles.material, sim.flip, sim.kernels.plan)
    grads = [StateGrad.zeros(device, n, dtype) for _ in range(2)]
    param_grad = DeviceArray.zeros(device, sim.particles.param.shape, dtype)
    mass_grad = DeviceArray.zeros(device, (n,), dtype)
    launches.clear()
    adjoint.run(state, after, tape, inputs, grads[0], grads[1], param_grad, mass_grad)
    backward = list(launches)
    assert_gpu_shaped(backward)
    assert len(backward) == ADJOINT_LAUNCHES[material], [x.kernel for x in backward]
    assert "g2p_adjoint_private" not in {x.kernel for x in backward}
    assert not [x.kernel for x in backward if x.kernel.endswith("_simd")]
    assert np.isfinite(param_grad.read().numpy()).all()


def test_the_check_sees_a_cpu_shape(device, launches, monkeypatch):
    """The same recording in the CPU plan flags its one-work-item scan and block sort: the
    check can fail."""
    from clflow.runtime.sort import sort_pairs

    monkeypatch.setenv("CLFLOW_KERNELS", "cpu")
    sort_pairs(torch.arange(100_000, dtype=torch.int32).flip(0), torch.arange(100_000, dtype=torch.int32), 17)
    with pytest.raises(AssertionError, match="scan_serial|radix_histogram"):
        assert_gpu_shaped(launches)


@pytest.mark.slow
def test_a_100k_gaussian_raster_call_is_gpu_shaped(device, launches):
    """bench raster's scene (100k Gaussians at 512^2), forward and backward: the tile sort's
    radix passes, the scans and the compositing are all work-group shaped."""
    from clflow.splat.ops import rasterize_gaussians
    from clflow_cli.bench.raster import make_scene

    args, kwargs = make_scene(100_000, 512, 512)
    leaves = [a.requires_grad_() for a in args[:5]]
    image, alpha, depth, meta = rasterize_gaussians(*args, **kwargs)
    (image.sum() + alpha.sum() + depth.sum()).backward()
    assert meta["num_tile_entries"] > 100_000 and all(leaf.grad is not None for leaf in leaves)
    assert_gpu_shaped(launches)
    names = {x.kernel for x in launches}
    assert {"rasterize_tiles_forward", "rasterize_tiles_backward", "radix_scatter_wg", "scan_blocks"} <= names
    assert not {"rasterize_forward", "rasterize_backward", "scan_serial", "radix_histogram"} & names


def test_a_100k_gaussian_scene_on_the_device_is_gpu_shaped(device, launches):
    """A run's flows (forward and backward) and its supersampled colour frames with a
    100k-Gaussian scene on the device (20k on the object, SH of degree 1): its own kernels
    (the frame's Gaussians, the mean-flow features, the polar rotations and SH colours, the
    byte conversion and the 2x average) a Gaussian, a value or a byte a
    work-item, and the rasteriser's work-group shaped."""
    from clflow.flow.scene_flow import render_scene_flows
    from clflow.pipeline.render import render_rgb_frames
    from clflow.splat.cameras import Camera
    from clflow.splat.device_scene import DeviceScene
    from clflow.splat.gaussians import Gaussians

    def gaussians(n, seed, spread, depth):
        g = torch.Generator().manual_seed(seed)
        means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * spread
        means[:, 2] += depth
        scales = 0.005 + 0.01 * torch.rand(n, 3, generator=g, dtype=torch.float64)
        sh = 0.3 * torch.randn(n, 4, 3, generator=g, dtype=torch.float64)
        quats, opacities = torch.randn(n, 4, generator=g, dtype=torch.float64), torch.full((n,), 0.6)
        return Gaussians.from_activated(means, quats, scales, opacities.double(), sh=sh).to(torch.float32)

    scene = DeviceScene(gaussians(80_000, 1, 2.0, 0.5), gaussians(20_000, 2, 0.6, 0.0))
    K = torch.tensor([[160.0, 0.0, 64.0], [0.0, 160.0, 64.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[2, 3] = 2.5
    cam = Camera(viewmat, K, 128, 128)
    rest = scene.obj_rest.means.double()
    x = torch.stack([rest + 0.01 * t for t in range(3)]).requires_grad_()
    F = torch.eye(3, dtype=torch.float64).expand(3, 20_000, 3, 3).contiguous().requires_grad_()
    sum(f.sum() for f in render_scene_flows(scene, x, F, cam)).backward()
    frames = render_rgb_frames(scene, x.detach(), F.detach(), cam, supersample=2)
    assert frames.shape == (3, 128, 128, 3) and x.grad is not None
    assert_gpu_shaped(launches)
    names = {x.kernel for x in launches}
    expected = {"object_frame", "mean_flow_features", "mean_flow_features_backward", "object_frame_backward"}
    assert expected | {"polar_rotation", "object_colors", "rgb_uint8", "area_average_uint8"} <= names
    assert "rasterize_tiles_forward" in names and "rasterize_forward" not in names
