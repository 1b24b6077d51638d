"""``clflow bench mpm``: MLS-MPM substep throughput per material (particle-substeps/s)."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option, double_option

PARTICLES_PER_AXIS = 64  # 64^3 = 262,144 particles: a cube of 32^3 cells at 2^3 per cell
GRID = 64


def _particle_bytes(sim) -> int:
    """Device bytes of every per-particle array of a simulator (``Simulator.particle_arrays``)."""
    return sum(a.nbytes for a in sim.particle_arrays())


def _run_peer(x, h: float, dx: float, grid_res: int, substeps: int, device, elastic: dict | None) -> dict:
    """taichi's MLS-MPM on the benchmark's lattice (clflow.peers.taichi_mpm), elastic at the
    registry's defaults and clflow's stable step; its figures and clflow's elastic against it."""
    from clflow.materials import get_material
    from clflow.mpm import Grid, MaterialSpec, Simulator
    from clflow.peers.taichi_mpm import run_taichi_mpm, taichi_version

    elastic_material = get_material("elastic")
    if elastic is not None:  # the step clflow's elastic run took
        dt = elastic["dt_s"]
    else:
        dt = Simulator(x, h**3, MaterialSpec("elastic"), Grid((grid_res,) * 3, dx), frame_dt=1e-3, device=device).dt
    arch = "cpu" if device.info.type == "CPU" else ("cuda" if "nvidia" in device.info.platform.lower() else "vulkan")
    timing = run_taichi_mpm(
        x.numpy(),
        grid_res,
        dx,
        dt,
        substeps,
        youngs_modulus=elastic_material.param("youngs_modulus").default,
        poissons_ratio=elastic_material.param("poissons_ratio").default,
        density=elastic_material.default_density,
        particle_volume=h**3,
        arch=arch,
    )
    rate = timing.particle_substeps_per_s
    ratio = elastic["particle_substeps_per_s"] / rate if elastic else None
    click.echo(
        f"{'taichi ' + arch:14s} {rate / 1e6:7.2f} M particle-substeps/s  ({timing.seconds / substeps * 1e3:6.1f} "
        f"ms/substep; taichi {taichi_version()}, elastic, float32, dt {dt:.3g} s; centre fell "
        f"{timing.centre_drop * 1e3:.3f} mm)" + (f"; clflow elastic / taichi: {ratio:.2f}x" if ratio else "")
    )
    return {
        "name": "taichi",
        "version": taichi_version(),
        "arch": arch,
        "particle_substeps_per_s": rate,
        "seconds": timing.seconds,
        "dt_s": dt,
        "centre_drop_m": timing.centre_drop,
        "clflow_elastic_over_peer": ratio,
    }


def timed_substeps(sim, substeps: int) -> None:
    """``substeps`` substeps of ``sim``, waited for (a substep only enqueues its kernels)."""
    for _ in range(substeps):
        sim.step()
    sim.device.finish()


@bench_command("mpm")
@count_option("--substeps", default=10, help="Timed substeps per material.")
@count_option('--particles-per-axis', default=PARTICLES_PER_AXIS, help="Particles per axis of the cube (total = cube of it).")  # fmt: skip
@click.option(
    "--grid", "grid_res", type=click.IntRange(min=8), default=GRID, show_default=True, help="Grid nodes per axis."
)
@click.option("--material", "materials", multiple=True, help="Only these materials (repeatable).")
@double_option
@click.option(
    "--peer",
    type=click.Choice(["taichi"]),
    help="Also run this peer's MLS-MPM (elastic, float32) on the same lattice, grid and step "
    "(taichi: the peers extra; its cpu backend on a CPU device, cuda on a GPU).",
)
@click.pass_context
def mpm(ctx, substeps, particles_per_axis, grid_res, materials, double, peer):
    """Particle-substeps per second of each material on a cube of particles under gravity,
    and the memory per particle. Also per CPU-second: on a machine shared with other jobs the
    wall-clock figure understates what the device does when it has its cores to itself."""
    import logging

    import torch

    from clflow.benchmark import measure
    from clflow.environment import load_average
    from clflow.materials import MATERIALS
    from clflow.mpm import Grid, MaterialSpec, Simulator
    from clflow.runtime import get_device

    device = ctx.obj.device() if ctx.obj else get_device()
    dtype = torch.float64 if double else torch.float32
    dx = 1.0 / grid_res
    side = (particles_per_axis / 2) * dx  # 2 particles per cell and axis
    h = side / particles_per_axis
    axis = 0.5 - side / 2 + h * (0.5 + torch.arange(particles_per_axis, dtype=torch.float64))
    x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    n = x.shape[0]
    names = list(materials) or list(MATERIALS)
    logging.getLogger("pyopencl").setLevel(logging.WARNING)  # no build chatter between rows
    click.echo(f"load average before the run: {load_average()} (figures scale down on a shared machine)")
    from clflow.mpm.substep import p2g_path

    p2g = {"private": "private grid copies", "atomic": "atomics", "gather": "gather over blocks of cells"}[
        p2g_path(device)
    ]
    memory = "separate memory" if not device.zero_copy else "shared memory"
    click.echo(
        f"device: {device.info.label} ({memory}; P2G: {p2g}); {n:,} particles, grid {grid_res}^3, "
        f"{'float64' if double else 'float32'}, {substeps} timed substeps"
    )
    results = {"particles": n}
    for name in names:
        sim = Simulator(
            x, h**3, MaterialSpec(name), Grid((grid_res,) * 3, dx), frame_dt=1e-3, dtype=dtype, device=device
        )
        timed_substeps(sim, 1)  # builds kernels and warms the caches
        mark = device.transfers.mark()
        timing = measure(lambda: timed_substeps(sim, substeps), warmup=0)
        copied = device.transfers.since(mark)
        elapsed, cpu = timing.median_wall, timing.median_cpu
        results[name] = {
            **timing.record(),
            "particle_substeps_per_s": n * substeps / elapsed,
            "dt_s": sim.dt,
            "bytes_per_particle": _particle_bytes(sim) // n,
            "bytes_to_device_per_substep": copied.to_device / substeps,
            "bytes_to_host_per_substep": copied.to_host / substeps,
        }
        click.echo(
            f"{name:14s} {n * substeps / elapsed / 1e6:7.2f} M particle-substeps/s  "
            f"({elapsed / substeps * 1e3:6.1f} ms/substep; {n * substeps / cpu / 1e6:5.2f} M per CPU-second; "
            f"{_particle_bytes(sim) // n} B/particle; copied per substep: {copied.to_device / substeps:.0f} B "
            f"to the device, {copied.to_host / substeps:.0f} B to the host)"
        )
    if peer:
        results["peer"] = _run_peer(x, h, dx, grid_res, substeps, device, results.get("elastic"))
    itemsize = torch.tensor([], dtype=dtype).element_size()
    grid_bytes = sim.grid.nodes * 7 * itemsize
    copies = getattr(sim.kernels, "copies", 0)
    click.echo(
        f"memory besides the particles: grid {grid_bytes / 2**20:.1f} MiB"
        + (f" + {copies} private P2G copies {copies * grid_bytes * 4 / 7 / 2**20:.1f} MiB" if copies else "")
    )
    return results
