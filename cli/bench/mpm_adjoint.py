"""``clflow bench mpm-adjoint``: backward (replay + adjoint) time against forward time of a
differentiable MPM run, and its peak memory against the checkpointing formula."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option, double_option


def _block(particles: int, h: float):
    """About ``particles`` positions [N, 3] m, (2 ny) x ny x ny at spacing ``h`` around (0.5, 0.5, 0.5)."""
    import torch

    ny = max(1, round((particles / 2) ** (1 / 3)))
    axes = [0.5 - (m * h) / 2 + h * (0.5 + torch.arange(m, dtype=torch.float64)) for m in (2 * ny, ny, ny)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _echo_times(forward: float, forward_cpu: float, backward: float, backward_cpu: float, work: int) -> None:
    """The forward's and backward's wall and CPU seconds (``work``: particle-substeps)."""
    click.echo(
        f"forward  {forward:8.2f} s  ({work / forward / 1e6:.2f} M particle-substeps/s); CPU {forward_cpu:.2f} s"
    )
    click.echo(
        f"backward {backward:8.2f} s  (replay + adjoint; {backward / forward:.2f}x forward, target <= 3x); "
        f"CPU {backward_cpu:.2f} s ({backward_cpu / forward_cpu:.2f}x: all threads of this process, "
        f"so other jobs on the machine barely change it)"
    )


def _echo_copies(copied: dict, steps: int, frames: int) -> None:
    """Bytes each pass copied between host and device, per substep and per frame."""
    for name, moved in copied.items():
        click.echo(
            f"{name:8s} copied {moved.to_device / 2**20:8.2f} MiB to the device, {moved.to_host / 2**20:8.2f} MiB "
            f"to the host: {moved.total / steps / 2**10:.1f} KiB per substep, {moved.total / frames / 2**20:.2f} MiB "
            f"per frame (each frame's x, v, F or their gradients)"
        )


@bench_command("mpm-adjoint")
@count_option("--particles", default=65536, help="Particles (a 2:1:1 block, 2 per cell and axis).")
@count_option("--grid", "grid_res", default=64, help="Grid nodes per axis.")
@count_option("--frames", default=10)
@count_option("--substeps", default=20, help="Substeps per frame.")
@double_option
@click.pass_context
def mpm_adjoint(ctx, particles, grid_res, frames, substeps, double):
    """Elastic block thrown against the floor: forward seconds, backward seconds (incl. replay),
    their ratio (target <= 3), and peak memory (measured RSS growth vs the formula)."""
    import resource

    import torch

    from clflow.benchmark import measure
    from clflow.mpm import Grid, MaterialSpec, Simulator
    from clflow.mpm.autograd import engine, memory_estimate, simulate
    from clflow.runtime import get_device

    device = ctx.obj.device() if ctx.obj else get_device()
    dtype = torch.float64 if double else torch.float32
    dx = 1.0 / grid_res
    h = dx / 2
    x = _block(particles, h)
    n = x.shape[0]
    v = torch.tensor([0.5, -1.0, 0.3], dtype=torch.float64).expand(n, 3)
    spec = MaterialSpec("elastic", {"youngs_modulus": 1e5, "poissons_ratio": 0.3})
    E = torch.tensor(1e5, dtype=dtype, requires_grad=True)
    # build every kernel once on a tiny copy of the scene (kernels do not depend on sizes), so
    # that the memory measured below is the run's own
    tiny = Simulator(
        x[:: max(1, n // 64)] * 0.2 + 0.4,
        h**3,
        spec,
        Grid((16,) * 3, 1 / 16),
        frame_dt=2e-3,
        substeps=2,
        dtype=dtype,
        device=device,
    )
    simulate(tiny, 1, params={"youngs_modulus": E}).x.sum().backward()
    sim = Simulator(
        x,
        h**3,
        spec,
        Grid((grid_res,) * 3, dx),
        velocities=v,
        frame_dt=substeps * 2e-4,
        substeps=substeps,
        dtype=dtype,
        device=device,
    )

    with open("/proc/self/statm") as statm:  # resident pages now (Linux)
        base = int(statm.read().split()[1]) * resource.getpagesize() / 2**20
    mark = device.transfers.mark()
    timed_forward = measure(lambda: simulate(sim, frames, params={"youngs_modulus": E}), warmup=0)
    between = device.transfers.mark()
    out, forward, forward_cpu = timed_forward.result, timed_forward.median_wall, timed_forward.median_cpu
    loss = (out.x[-1] ** 2).sum() + (out.F[-1] ** 2).sum()
    timed_backward = measure(loss.backward, warmup=0)
    copied = {"forward": between.since(mark), "backward": device.transfers.since(between)}
    backward, backward_cpu = timed_backward.median_wall, timed_backward.median_cpu
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base  # MiB
    steps = frames * substeps
    memory = "separate memory" if not device.zero_copy else "shared memory"
    click.echo(
        f"device: {device.info.label} ({memory}); {n:,} particles, grid {grid_res}^3, "
        f"{frames} frames x {substeps} substeps, {'float64' if double else 'float32'}"
    )
    _echo_times(forward, forward_cpu, backward, backward_cpu, n * steps)
    adjoint = engine(sim).adjoint  # its scatter follows the path the plan took, not the forward P2G's
    copies = 0 if adjoint.gather else adjoint.copies
    est = memory_estimate(n, sim.grid.nodes, frames, substeps, dtype, grid_copies=copies) / 2**20
    click.echo(f"peak memory growth {peak:8.1f} MiB (peak RSS - RSS before the run); formula {est:.1f} MiB")
    _echo_copies(copied, steps, frames)
    return {
        "particles": n,
        **{
            name: {**timed.record(), "bytes_to_device": copied[name].to_device, "bytes_to_host": copied[name].to_host}
            for name, timed in (("forward", timed_forward), ("backward", timed_backward))
        },
        "backward_over_forward": backward / forward,
        "peak_memory_mib": peak,
        "formula_memory_mib": est,
    }
