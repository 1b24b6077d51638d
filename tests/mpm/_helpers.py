"""Small scenes the MPM tests share."""

from __future__ import annotations

import torch

from clflow.mpm import Grid, MaterialSpec, Simulator

# Parameters that make every material's return mapping active within a few substeps of
# the random-velocity scene below (checked by test_substep.py).
MATERIAL_CASES: dict[str, dict[str, float]] = {
    "elastic": {"youngs_modulus": 1e4, "poissons_ratio": 0.3},
    "plasticine": {"youngs_modulus": 1e4, "poissons_ratio": 0.3, "yield_stress": 300.0},
    "metal": {"youngs_modulus": 1e4, "poissons_ratio": 0.3, "yield_stress": 300.0, "hardening": 1.0},
    "foam": {"youngs_modulus": 1e4, "poissons_ratio": 0.3, "yield_stress": 300.0, "viscosity": 0.05},
    "sand": {"youngs_modulus": 1e4, "poissons_ratio": 0.3, "friction_angle": 35.0, "cohesion": 0.001},
    "newtonian": {"viscosity": 1.0, "bulk_modulus": 1e4},
    "non_newtonian": {"shear_modulus": 2e3, "bulk_modulus": 1e4, "yield_stress": 80.0, "viscosity": 0.05},
    "snow": {"youngs_modulus": 1e4, "poissons_ratio": 0.2},
}


def cube(n_side: int, lower: float, upper: float, dtype=torch.float64) -> torch.Tensor:
    """n_side^3 particles on a regular lattice filling [lower, upper]^3 (m)."""
    h = (upper - lower) / n_side
    axis = lower + h * (0.5 + torch.arange(n_side, dtype=dtype))
    return torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)


def free_body(x: torch.Tensor, material: MaterialSpec, grid: Grid, **kwargs) -> Simulator:
    """Particles ``x`` (N, 3) m of 1e-5 m^3 each with no gravity and no walls (so momentum is
    the forces' alone); float64, 20 substeps of 0.02 s frames unless ``kwargs`` say otherwise."""
    kwargs = {"frame_dt": 0.02, "substeps": 20, "dtype": torch.float64, **kwargs}
    return Simulator(x, 1e-5, material, grid, gravity=(0, 0, 0), walls=None, **kwargs)


# sand with Tampubolon et al.'s volume correction (a model option of sand)
VOLUME_CORRECTED_SAND = MaterialSpec("sand", MATERIAL_CASES["sand"], model="volume_corrected")


def moving_scene(x: torch.Tensor, v: torch.Tensor, materials, grid: Grid, dtype=torch.float64, **kwargs) -> Simulator:
    """Particles ``x`` [N, 3] m of 1e-5 m^3 each with velocities ``v`` [N, 3] m/s on ``grid``,
    one material per particle cycling through ``materials`` ({name: params}, or a list of
    MaterialSpec); 10 substeps of 0.01 s frames unless ``kwargs`` say otherwise."""
    if isinstance(materials, dict):
        specs = [MaterialSpec(name, params) for name, params in materials.items()]
    else:
        specs = list(materials)
    kwargs = {"substeps": 10, "frame_dt": 1e-2, **kwargs}
    index = torch.arange(x.shape[0]) % len(specs)
    return Simulator(x, 1e-5, specs, grid, velocities=v, dtype=dtype, material_index=index, **kwargs)


def random_scene(materials, seed: int = 0, n: int = 300, dtype=torch.float64, **kwargs) -> Simulator:
    """Particles at random in [0.3, 0.7]^3 m on a 16^3 grid of 1/16 m, with random velocities
    (so stresses and yield are exercised): :func:`moving_scene`."""
    gen = torch.Generator().manual_seed(seed)
    x = 0.3 + 0.4 * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    v = 0.6 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    return moving_scene(x, v, materials, Grid((16, 16, 16), 1 / 16), dtype, **kwargs)


def tiny_plasticine(flip: float = 0.0, **kwargs) -> Simulator:
    """13 plasticine particles, 2 substeps a frame, no walls (``kwargs``: random_scene's):
    the smallest scene whose kernels oclgrind checks."""
    return random_scene({"plasticine": MATERIAL_CASES["plasticine"]}, n=13, substeps=2, frame_dt=2e-4, walls=None,
                        flip=flip, **kwargs)  # fmt: skip


def assert_velocity_gradient(sim: Simulator) -> None:
    """One frame's sum(x^2) has a finite, non-zero gradient in the initial velocities."""
    from clflow.mpm.autograd import simulate

    v0 = sim.state.v.clone().requires_grad_()
    (simulate(sim, 1, velocities=v0).x ** 2).sum().backward()
    assert bool(torch.isfinite(v0.grad).all()) and float(v0.grad.abs().sum()) > 0


def two_blocks(materials=("newtonian",), n_side: int = 5, dtype=torch.float64, **kwargs) -> Simulator:
    """Two blocks of n_side^3 particles each, 0.45 m apart in a 32^3 grid of 1/32 m, moving
    towards each other (the private P2G path unless ``kwargs`` say otherwise): each private
    grid copy's particle chunk lies mostly in one block, so its box of touched nodes
    (chunk_box) is a small part of the grid and moves between substeps."""
    gen = torch.Generator().manual_seed(0)
    x = torch.cat([cube(n_side, 0.2, 0.3), cube(n_side, 0.65, 0.75)])
    v = torch.ones_like(x) * torch.sign(0.5 - x[:, :1]) + 0.3 * torch.randn(x.shape, generator=gen, dtype=x.dtype)
    specs = {name: MATERIAL_CASES[name] for name in materials}
    return moving_scene(x, v, specs, Grid((32, 32, 32), 1 / 32), dtype, **{"p2g": "private", **kwargs})


def poison(device, buffer) -> None:
    """Fill an OpenCL buffer with all bits set, a NaN in float32 and float64 alike: stale memory
    that no sum may read."""
    import numpy as np
    import pyopencl as cl

    cl.enqueue_fill_buffer(device.queue, buffer, np.full(1, 255, np.uint8), 0, buffer.size)
    device.finish()


#: relative agreement of two runs on the atomic P2G path, whose sums take the order the
#: work-items happen to run in (float32: return mappings amplify round-off near the yield
#: surface, 1.4e-5 seen on PoCL)
ATOMIC_REPEAT_TOL = {torch.float32: 1e-4, torch.float64: 1e-9}


def loss_rounding(sim: Simulator) -> float:
    """Relative error of one run's loss that a difference quotient cannot resolve: rounding of
    the sum on the deterministic P2G paths; on the atomic one two runs of the same point differ
    too (the swirling block's losses spread up to 1e-14 over 6 runs, a quotient's ends 3e-14
    apart seen in CI on PoCL), so ten times that."""
    return 1e-14 if sim.kernels.p2g in ("private", "gather") else 1e-13


def assert_repeats(a: torch.Tensor, b: torch.Tensor, sim: Simulator, what: str = "") -> None:
    """``a`` and ``b`` from two runs of the same computation on ``sim``'s kernels: bit-identical
    on the deterministic P2G paths (private grid copies, the gather over blocks: fixed orders),
    within ATOMIC_REPEAT_TOL on the atomic one."""
    if sim.kernels.p2g in ("private", "gather"):
        assert torch.equal(a, b), what
    else:
        scale = b.abs().max().clamp(min=1e-30)
        assert float((a - b).abs().max() / scale) < ATOMIC_REPEAT_TOL[a.dtype], what


def assert_clean_under_oclgrind(oclgrind, script: str) -> None:
    """Run ``script`` (it prints "done on <device>") with the ``oclgrind`` fixture: it must
    finish on the Oclgrind device and oclgrind must report nothing. No uninitialised-value
    checks: with them Oclgrind 21.10 segfaults on the MPM kernels."""
    out, report = oclgrind(script, timeout=900, uninitialized=False)
    assert "done on Oclgrind" in out, out[-500:]
    assert report.strip() == "", report[:3000]
