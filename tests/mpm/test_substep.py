"""The OpenCL substep against the pure-torch reference (float64), determinism, P2G paths."""

import pytest
import torch

from clflow.mpm import Grid, reference
from clflow.mpm.constants import MATERIAL_IDS
from tests.mpm._helpers import (
    MATERIAL_CASES,
    assert_repeats,
    cube,
    moving_scene,
    poison,
    random_scene,
    two_blocks,
)

FIELDS = ("x", "v", "C", "F", "plastic")


def rel_diff(a, b) -> float:
    """max |a - b| / max |b|; inf where either holds a NaN (max() would pass over it)."""
    diff = float((a - b).abs().max() / b.abs().max().clamp(min=1e-30))
    return diff if diff == diff else float("inf")


def run_both(sim, substeps):
    """Step the simulator and the reference side by side; returns the worst relative diff."""
    ref = sim.state.clone()
    worst = 0.0
    for _ in range(substeps):
        t = sim.time
        sim.step()
        ref, _ = reference.substep(
            ref,
            sim.particles,
            sim.grid,
            t,
            sim.dt,
            sim.gravity,
            sim.boundaries,
            sim.drivers.accel(t, sim.dtype),
            sim.flip,
        )
        worst = max(worst, *(rel_diff(getattr(sim.state, f), getattr(ref, f)) for f in FIELDS))
    return worst


@pytest.mark.parametrize("substeps", [1, 20])
@pytest.mark.parametrize("material", list(MATERIAL_CASES))
def test_matches_reference_float64(material, substeps):
    sim = random_scene({material: MATERIAL_CASES[material]})  # 300 particles: a partial SIMD tail
    # elastic-only scenes take the fused stress kernel; the others the SVD (but the J-only
    # Newtonian fluid; inline in the GPU plan's gather) and the per-particle model kernel
    assert sim.kernels.elastic_only == (material == "elastic")
    svd_launch = material not in ("elastic", "newtonian") and not sim.kernels.plan.stress_keys_cells
    assert (sim.kernels.k_svd is not None) == svd_launch
    assert run_both(sim, substeps) < 1e-9


@pytest.mark.parametrize("flip", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("p2g", ["private", "atomic", "gather"])
def test_flip_blend_matches_reference(flip, p2g):
    """APIC and the PIC/FLIP blend (every material, walls and a floor, 20 substeps) on every P2G path."""
    from clflow.mpm import HalfSpace

    sim = random_scene(
        MATERIAL_CASES, n=400, flip=flip, p2g=p2g, boundaries=[HalfSpace((0, 0.4, 0), (0, 1, 0), "sticky")]
    )
    assert sim.kernels.scratch.grid_mv.shape[1] == (7 if flip else 4) and sim.kernels.p2g == p2g
    assert run_both(sim, 20) < 1e-9


def test_flip_blend_keeps_the_particle_velocity():
    """With flip = 1 and no forces a particle keeps its own velocity (plus the grid's change,
    here none); APIC replaces it by the grid's smoothed field."""
    from clflow.mpm import Grid, MaterialSpec, Simulator

    gen = torch.Generator().manual_seed(3)
    x = 0.4 + 0.2 * torch.rand(200, 3, generator=gen, dtype=torch.float64)
    v = 0.1 * torch.randn(200, 3, generator=gen, dtype=torch.float64)
    kept = {}
    for flip in (0.0, 1.0):
        sim = Simulator(
            x,
            1e-5,
            MaterialSpec("newtonian", {"viscosity": 0.0, "bulk_modulus": 1.0}),
            Grid((16, 16, 16), 1 / 16),
            velocities=v,
            gravity=(0, 0, 0),
            walls=None,
            substeps=1,
            frame_dt=1e-4,
            dtype=torch.float64,
            flip=flip,
        )
        sim.step()
        kept[flip] = rel_diff(sim.state.v, v)
    assert kept[1.0] < 1e-12
    assert kept[0.0] > 0.1


def test_neo_hookean_matches_reference():
    from clflow.mpm import Grid, MaterialSpec, Simulator

    gen = torch.Generator().manual_seed(1)
    x = 0.3 + 0.4 * torch.rand(200, 3, generator=gen, dtype=torch.float64)
    sim = Simulator(
        x,
        1e-5,
        MaterialSpec("elastic", MATERIAL_CASES["elastic"], model="neo_hookean"),
        Grid((16, 16, 16), 1 / 16),
        velocities=0.6 * torch.randn(200, 3, generator=gen, dtype=torch.float64),
        dtype=torch.float64,
        substeps=10,
        frame_dt=1e-2,
    )
    assert int(sim.particles.material[0]) == MATERIAL_IDS["neo_hookean"]
    assert run_both(sim, 20) < 1e-9


def test_mixed_materials_match_reference():
    sim = random_scene(MATERIAL_CASES, n=400)
    assert len(sim.particles.material.unique()) == len(MATERIAL_CASES)
    assert run_both(sim, 20) < 1e-9


@pytest.mark.parametrize("material", ["plasticine", "metal", "foam", "sand", "non_newtonian", "snow"])
def test_scene_exercises_the_return_mapping(material):
    """The agreement tests above are only meaningful if some particles yield and some not."""
    sim = random_scene({material: MATERIAL_CASES[material]})
    for _ in range(5):
        sim.step()
    s = sim.state
    F_tr = (torch.eye(3, dtype=s.F.dtype) + sim.dt * s.C) @ s.F
    F_new, _, _ = reference.constitutive(MATERIAL_IDS[material], F_tr, s.C, sim.particles.param, s.plastic, sim.dt)
    changed = (F_new - F_tr).abs().amax((1, 2)) > 1e-12
    assert 0 < int(changed.sum()) < sim.n


@pytest.mark.parametrize("p2g", ["private", "atomic", "gather"])
@pytest.mark.parametrize("materials", [MATERIAL_CASES, {"elastic": MATERIAL_CASES["elastic"]}])
def test_repeated_runs_float32(materials, p2g):
    """Private grid copies and the gather over blocks sum in fixed orders: two runs are
    bit-identical. Atomic adds sum in the order the work-items happen to run, so the last
    bits differ between runs; they agree to ATOMIC_REPEAT_TOL."""
    runs = []
    for _ in range(2):
        sim = random_scene(materials, dtype=torch.float32, n=500, p2g=p2g)
        for _ in range(10):
            sim.step()
        runs.append(sim.state.clone())
    assert sim.kernels.p2g == p2g
    for f in FIELDS:
        assert_repeats(getattr(runs[0], f), getattr(runs[1], f), sim, f)


def test_private_copies_reduce_in_fixed_order():
    """Several private grid copies are in use (the deterministic CPU path)."""
    sim = random_scene({"elastic": MATERIAL_CASES["elastic"]}, p2g="private")
    assert sim.kernels.p2g == "private" and sim.kernels.copies >= 2


@pytest.mark.parametrize("flip", [0.0, 0.99])
def test_private_copies_are_zeroed_and_summed_only_in_their_boxes(flip):
    """Each private grid copy is zeroed and summed only in the box of nodes its particle chunk
    touches: with the copies full of NaN beforehand, 20 substeps of two blocks that move
    towards each other still match the reference, while every box is a small part of the grid."""
    sim = two_blocks(("newtonian", "elastic"), flip=flip)
    poison(sim.device, sim.kernels.grid_copies)
    assert run_both(sim, 20) < 1e-9
    boxes = sim.kernels.copy_boxes.read()
    volumes = (boxes[:, 3:] - boxes[:, :3]).prod(1)
    assert sim.kernels.copies >= 2 and int(volumes.max()) <= sim.grid.nodes // 4, boxes


def stacked_blocks(flip: float):
    """Two blocks one above the other along z (the grid's rows), moving towards each other:
    the copies of the lower block's chunks and those of the upper one's share rows of nodes
    with different ranges of k."""
    gen = torch.Generator().manual_seed(1)
    block = cube(5, 0.2, 0.3)
    x = torch.cat([block, block + torch.tensor([0.05, 0.0, 0.45], dtype=block.dtype)])
    v = torch.zeros_like(x)
    v[:, 2] = torch.sign(0.5 - x[:, 2]) + 0.3 * torch.randn(x.shape[0], generator=gen, dtype=x.dtype)
    specs = {"newtonian": MATERIAL_CASES["newtonian"]}
    return moving_scene(x, v, specs, Grid((32, 32, 32), 1 / 32), torch.float64, flip=flip, p2g="private")


@pytest.mark.parametrize("flip", [0.0, 0.99])
@pytest.mark.parametrize("scene", ["two_blocks", "stacked_blocks"])
def test_the_private_paths_grid_update_equals_grid_update_on_every_node(flip, scene):
    """sum_copies_update_grid updates only the nodes inside a copy's box and writes zero
    elsewhere: with the grid velocities full of NaN beforehand, each substep's velocities (and
    their change) equal to the bit what grid_update makes of the same summed grid, on every node
    (stacked_blocks: rows that boxes with different ranges of k share)."""
    import numpy as np

    if scene == "two_blocks":
        sim = two_blocks(("newtonian", "elastic"), flip=flip)
    else:
        sim = stacked_blocks(flip)
    kernels, tape = sim.kernels, sim.kernels.scratch
    update = sim.device.kernel("mpm/grid.cl", "grid_update", kernels.real, kernels.defines)
    for _ in range(5):
        poison(sim.device, tape.grid_v.buffer)
        poison(sim.device, tape.grid_dv.buffer)
        inputs = sim.substep_inputs()
        sim.step()
        fields = (tape.grid_v, tape.grid_dv) if flip else (tape.grid_v,)  # APIC: grid_dv is [1, 3], unused
        got = tuple(f.read() for f in fields)
        grids = dict(grid=tape.grid_mv, grid_v=tape.grid_v, grid_dv=tape.grid_dv)
        sim.device.launch(update, sim.grid.nodes, kernels.grid_args | inputs.grid_update_args(kernels.real_t) | grids)
        want = tuple(f.read() for f in fields)
        for g, w in zip(got, want):
            assert torch.isfinite(w).all() and torch.equal(g, w)
    assert (got[0][tape.grid_mv.read()[:, 0] == 0] == 0).all() and np.any(got[0].numpy() != 0)


def test_the_p2g_path_follows_the_plan_unless_forced(device, monkeypatch):
    """The plan records the P2G path taken: its own, else $CLFLOW_P2G, else the simulator's
    request; the adjoint's scatter takes a private or gather P2G's shape."""
    from clflow.errors import InputError
    from clflow.mpm.substep import p2g_path
    from clflow.runtime.plan import KERNELS_ENV, P2G_ENV, kernel_plan

    monkeypatch.delenv(P2G_ENV, raising=False)
    for kind, path in (("cpu", "private"), ("gpu", "gather")):
        monkeypatch.setenv(KERNELS_ENV, kind)
        assert p2g_path(device) == path and kernel_plan(device).adjoint_scatter == path
    assert p2g_path(device, "atomic") == "atomic"
    assert kernel_plan(device, "private").adjoint_scatter == "private"  # the GPU plan, P2G private
    assert kernel_plan(device, "atomic").adjoint_scatter == "gather"  # no atomic adjoint: the plan's own
    monkeypatch.setenv(P2G_ENV, "atomic")
    assert p2g_path(device) == "atomic" and kernel_plan(device).p2g == "atomic"
    assert p2g_path(device, "private") == "private"  # an explicit choice wins over the variable
    monkeypatch.setenv(P2G_ENV, "fast")
    with pytest.raises(InputError, match="CLFLOW_P2G must be one of"):
        p2g_path(device)


def test_the_memory_check_counts_the_path_taken(device, monkeypatch):
    """The grid's memory check counts what the plan's P2G path takes beside the grid: a
    private copy of its sums, the gather's tiles of sums (about 3.4 times them), or nothing
    (atomics): a device with room for the grid and a copy refuses the gather alone."""
    import dataclasses
    import types

    from clflow.errors import InputError
    from clflow.mpm.substep import check_grid_memory, p2g_partial_reals
    from clflow.runtime.plan import KERNELS_ENV, P2G_ENV, kernel_plan

    monkeypatch.setenv(KERNELS_ENV, "cpu")
    monkeypatch.delenv(P2G_ENV, raising=False)
    grid = Grid((32, 32, 32), 1 / 32)
    nodes_bytes = grid.nodes * 8 * (4 + 3)  # float64 (m, mv) and v per node

    def device_of(size: int):
        return types.SimpleNamespace(info=dataclasses.replace(device.info, global_mem_size=size))

    small, with_copy = device_of(nodes_bytes + 1), device_of(nodes_bytes + grid.nodes * 8 * 4 + 1)
    check_grid_memory(small, grid, 8, plan=kernel_plan(small, "atomic"))
    for path in ("private", "gather"):
        with pytest.raises(InputError, match="of device memory"):
            check_grid_memory(small, grid, 8, plan=kernel_plan(small, path))
    check_grid_memory(with_copy, grid, 8, plan=kernel_plan(with_copy, "private"))
    with pytest.raises(InputError, match="of device memory"):
        check_grid_memory(with_copy, grid, 8, plan=kernel_plan(with_copy, "gather"))
    with_tiles = device_of(nodes_bytes + 8 * p2g_partial_reals(grid.nodes) + 1)
    monkeypatch.setenv(P2G_ENV, "gather")
    check_grid_memory(with_tiles, grid, 8)  # the device's plan, with $CLFLOW_P2G's path


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_the_p2g_paths_agree(dtype, tol):
    sims = [random_scene(MATERIAL_CASES, dtype=dtype, p2g=mode) for mode in ("private", "atomic", "gather")]
    for sim in sims:
        for _ in range(10):
            sim.step()
    for other in sims[1:]:
        for f in FIELDS:
            assert rel_diff(getattr(other.state, f), getattr(sims[0].state, f)) < tol, (other.kernels.p2g, f)


def test_the_gather_sorts_particles_by_cell_and_sums_each_node_in_that_order():
    """Particles crossing cells between substeps (random velocities): the cell lists are
    rebuilt every substep, every particle in exactly one list, in index order within its cell,
    the cell its position says, and the gather's grid equals the private copies' to round-off."""
    from clflow.runtime.arrays import DeviceArray

    sims = [random_scene(MATERIAL_CASES, n=700, p2g=mode) for mode in ("private", "gather")]
    for sim in sims:
        for _ in range(5):
            sim.step()
    tapes = []
    for sim in sims:
        tapes.append(sim.kernels.empty_tape())
        state = sim.device_state
        clamped = DeviceArray.zeros(sim.device, (sim.n,), torch.uint8)
        sim.kernels.run(state, state.empty_like(), sim.substep_inputs(), clamped, tapes[-1])
    assert rel_diff(tapes[1].grid_mv.read(), tapes[0].grid_mv.read()) < 1e-12
    gather, tape = sims[1], tapes[1]  # its tape holds the sort at the gather's current state
    assert tape.sorted_by_cell and not tapes[0].sorted_by_cell
    starts, order = tape.starts.read().long(), tape.order.read().long()
    counts = starts.diff()
    assert int(counts.sum()) == gather.n and int(counts.max()) > 1  # each particle once; cells shared
    xi = (gather.state.x.double() - torch.tensor(gather.grid.origin, dtype=torch.float64)) / gather.grid.dx
    upper = torch.tensor(gather.grid.resolution) - 3
    base = torch.minimum(torch.floor(xi - 0.5).long().clamp(min=0), upper)
    nx, ny, nz = gather.grid.resolution
    cell = (base[:, 0] * ny + base[:, 1]) * nz + base[:, 2]
    assert torch.equal(order, torch.sort(cell, stable=True).indices)  # by cell, then index


def test_the_cell_occupancy_counts_the_runs_the_gather_sorts():
    """clflow bench optimize's scene shape (cell_occupancy, on the host) is the gather's own
    cell sort: the same occupied cells and the same runs."""
    from clflow.mpm.substep import cell_occupancy
    from clflow.runtime.arrays import DeviceArray

    sim = random_scene(MATERIAL_CASES, n=700, p2g="gather")
    for _ in range(3):
        sim.step()
    tape, state = sim.kernels.empty_tape(), sim.device_state
    sim.kernels.run(
        state, state.empty_like(), sim.substep_inputs(), DeviceArray.zeros(sim.device, (sim.n,), torch.uint8), tape
    )
    runs = tape.starts.read().long().diff()
    runs = runs[runs > 0].double()
    shape = cell_occupancy(sim.grid, sim.state.x)
    assert (shape.particles, shape.occupied_cells, shape.run_max) == (sim.n, len(runs), int(runs.max()))
    assert (shape.run_median, shape.run_p99) == (float(runs.median()), float(torch.quantile(runs, 0.99)))
    assert shape.cells == torch.prod(torch.tensor(sim.grid.resolution) - 2)


def test_the_cell_occupancy_of_a_placed_cluster():
    """Nine particles: eight in one base cell, one four cells along x (the next block of
    P2G_BLOCK^3 cells), on a 12^3 grid of 10^3 base cells in 3^3 blocks."""
    from clflow.mpm.substep import cell_occupancy

    grid = Grid((12, 12, 12), 0.1, origin=(-0.5, 0.0, 0.0))
    x = torch.tensor([[-0.5 + 0.26 + 0.01 * k, 0.27, 0.28] for k in range(8)] + [[-0.5 + 0.66, 0.27, 0.28]])
    shape = cell_occupancy(grid, x)
    assert (shape.cells, shape.occupied_cells, shape.blocks, shape.occupied_blocks) == (1000, 2, 27, 2)
    assert (shape.run_median, shape.run_max) == (1.0, 8)
    assert "9 particles in 2 of 1,000 cells (2 of 27 blocks of 4^3)" in shape.summary()


@pytest.mark.parametrize("flip", [0.0, 0.95])
def test_the_gather_reads_each_particle_once_and_sums_as_the_private_copies(flip):
    """The gather P2G over blocks of cells reads each particle from global memory once a
    substep (counted by the kernel itself), in a scene of 400 particles in two cells (runs
    staged over several stages) beside sparse ones, and its grid equals the private copies'
    to round-off."""
    from clflow.mpm.substep import SubstepKernels
    from clflow.runtime.arrays import DeviceArray

    gen = torch.Generator().manual_seed(3)
    dense = 0.5 + 0.05 * torch.rand(400, 3, generator=gen, dtype=torch.float64)  # cells of 1/16 m
    sparse = 0.2 + 0.6 * torch.rand(300, 3, generator=gen, dtype=torch.float64)
    x = torch.cat([dense, sparse])
    v = 0.3 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    sims = [
        moving_scene(x, v, MATERIAL_CASES, Grid((16, 16, 16), 1 / 16), p2g=mode, flip=flip)
        for mode in ("private", "gather")
    ]
    grids = []
    for sim in sims:
        sim.step()
        kernels = SubstepKernels(
            sim.device, sim.dtype, sim.n, sim.grid, sim.particles.material, sim.kernels.p2g, sim.flip, count_reads=True
        )
        tape, state = kernels.empty_tape(), sim.device_state
        clamped = DeviceArray.zeros(sim.device, (sim.n,), torch.uint8)
        kernels.run(state, state.empty_like(), sim.substep_inputs(), clamped, tape)
        grids.append(tape.grid_mv.read())
    assert int(kernels.p2g_reads.read()[0]) == sims[1].n
    assert rel_diff(grids[1], grids[0]) < 1e-12
