"""``clflow bench launch``: the host's side of a substep, where a GPU waits for its host.

A small scene's substep is bound by the host's time to enqueue it, not by the device: this
times the substep loop (host time and wall time per substep) at a few particle counts and
for a population of the smallest scene (clflow.mpm.population: its members share each
substep's launches, so the host's time per member-substep falls with their number),
counts a substep's launches, and times one launch's phases on two of the substep's kernels:
the argument table (``KernelSignature.ordered``) and the binding, paid once per set of
arrays (clflow.runtime.binding), then pyopencl's ``set_args`` and the driver's enqueue,
paid by every substep.
"""

import time

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option

SIZES = ((8, 16), (16, 32), (32, 48))  # (particles per axis, grid nodes per axis)
#: kernels whose launches can repeat without changing what they read (grid update, G2P):
#: the phases are timed on them
REPEATABLE = ("sum_copies_update_grid", "p2g_blocks_update", "g2p_sorted", "g2p")
POPULATION = 24  # members of the population timed (a global search's samples)


def _cube(particles_per_axis: int, grid_res: int):
    """(x [n, 3] m, particle volume m^3, material, grid): a cube of elastic particles, 2 per
    cell and axis, in the middle of a unit domain."""
    import torch

    from clflow.mpm import Grid, MaterialSpec

    dx = 1.0 / grid_res
    h = dx / 2
    axis = 0.5 - particles_per_axis * h / 2 + h * (0.5 + torch.arange(particles_per_axis, dtype=torch.float64))
    x = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return x, h**3, MaterialSpec("elastic"), Grid((grid_res,) * 3, dx)


def _time_substeps(device, sim, substeps: int) -> tuple[float, float, float]:
    """(host, host thread CPU, wall) seconds of ``substeps`` substeps of ``sim``, after 10 that build and warm."""
    for _ in range(10):
        sim.step()
    device.finish()
    started, started_cpu = time.perf_counter(), time.thread_time()
    for _ in range(substeps):
        sim.step()
    host, host_cpu = time.perf_counter() - started, time.thread_time() - started_cpu
    device.finish()
    return host, host_cpu, time.perf_counter() - started


def _per_call_us(fn, calls: int) -> float:
    started = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - started) / calls * 1e6


def _substep_recording(device, sim):
    """(the next substep's launches bound, not enqueued; each launch's (kernel, global size,
    arguments, local size) as the substep asked for it)."""
    import torch

    from clflow.runtime.arrays import DeviceArray

    asked, bind = [], device.bind
    device.bind = lambda kernel, size, args, local_size: (
        asked.append((kernel, size, args, local_size)) or bind(kernel, size, args, local_size)
    )
    try:
        state = sim.device_state
        clamped = DeviceArray.zeros(device, (sim.n,), torch.uint8)
        recording = sim.kernels.record(state, state.empty_like(), sim.substep_inputs(), clamped)
    finally:
        del device.bind  # the class's method again
    return recording, asked


def _launch_phases(device, asked, calls: int) -> dict:
    """Microseconds per call of each phase of a launch, on the REPEATABLE kernels of one substep:
    the argument table and binding (paid once per set of arrays: clflow.runtime.binding),
    set_args and the driver's enqueue (paid by every substep), a whole unbound launch."""
    import pyopencl as cl

    phases = {}
    for kernel, size, args, local_size in asked:
        if kernel.function_name not in REPEATABLE:
            continue
        signature = device.signature(kernel)
        bound = device.bind(kernel, size, args, local_size)
        ordered = _per_call_us(lambda: signature.ordered(args), calls)
        binding = _per_call_us(lambda: device.bind(kernel, size, args, local_size), calls)
        set_args = _per_call_us(lambda: kernel.set_args(*bound.raw), calls)
        device.finish()
        queue, gsize, lsize = device.queue, bound.global_size, bound.local_size
        enqueue = _per_call_us(lambda: cl.enqueue_nd_range_kernel(queue, kernel, gsize, lsize), calls)
        device.finish()
        launch = _per_call_us(lambda: device.launch(kernel, size, args, local_size), calls)
        device.finish()
        phases[kernel.function_name] = {
            "arguments": len(bound.raw),
            "ordered_us": ordered,
            "bind_us": binding,
            "set_args_us": set_args,
            "enqueue_us": enqueue,
            "launch_us": launch,
        }
        click.echo(
            f"  {kernel.function_name:12s} {len(bound.raw):2d} arguments: table {ordered:5.1f} us (bound {binding:5.1f}"
            f" us, once), set_args {set_args:5.1f} us, enqueue {enqueue:5.1f} us; an unbound launch {launch:5.1f} us"
        )
    return phases


@bench_command("launch")
@count_option("--substeps", default=300, help="Timed substeps per size.")
@count_option("--calls", default=500, help="Timed calls of each launch phase.")
@click.pass_context
def launch(ctx, substeps, calls):
    """Host time per substep (no profile: its events cost time too) at 512, 4,096 and 32,768
    particles, for a population of 24 members of the smallest scene (per member-substep,
    against a single run's substep), and per launch: the argument table, set_args and the
    driver's enqueue (the kernel plan: the device's, or $CLFLOW_KERNELS's). Where
    a substep's wall time equals its host time, the device waits for the host. The host's
    own CPU time (its thread's) is given too: on a CPU device the device's threads share the
    cores, and the host's time then includes waiting for one."""
    from clflow.environment import load_average
    from clflow.mpm import Simulator
    from clflow.runtime import get_device
    from clflow.runtime.binding import BoundLaunch

    device = ctx.obj.device() if ctx.obj else get_device()
    click.echo(f"device: {device.info.label}; load average before the run: {load_average()}")
    results = {"sizes": {}}
    for particles_per_axis, grid_res in SIZES:
        x, volume, material, grid = _cube(particles_per_axis, grid_res)
        sim = Simulator(x, volume, material, grid, frame_dt=1e-3, device=device)
        host, host_cpu, wall = _time_substeps(device, sim, substeps)
        n, us = x.shape[0], 1e6 / substeps
        results["sizes"][str(n)] = {
            "grid": grid_res,
            "host_us_per_substep": host * us,
            "host_cpu_us_per_substep": host_cpu * us,
            "wall_us_per_substep": wall * us,
        }
        click.echo(
            f"{n:7,d} particles, grid {grid_res}^3: {host * us:7.1f} us of host time a substep "
            f"({host_cpu * us:6.1f} us on its thread), {wall * us:7.1f} us of wall time"
        )
    results["population"] = _population(device, substeps, results["sizes"])
    recording, asked = _substep_recording(device, sim)
    launches = sum(isinstance(step, BoundLaunch) for step in recording.steps)
    results["launches_per_substep"] = launches
    results["plan"] = sim.kernels.plan.describe()
    click.echo(f"a substep: {launches} launches ({sim.kernels.plan.describe()})")
    click.echo("one launch, by phase:")
    results["phases"] = _launch_phases(device, asked, calls)
    return results


def _population(device, substeps: int, sizes: dict) -> dict:
    """The smallest scene as a population of POPULATION members (Young's moduli 1e4-1e5 Pa):
    host time per member-substep against the single run's per substep (``sizes``' first)."""
    import torch

    from clflow.mpm import MaterialSpec, Simulator

    particles_per_axis, grid_res = SIZES[0]
    x, volume, _, grid = _cube(particles_per_axis, grid_res)
    moduli = torch.logspace(4, 5, POPULATION, dtype=torch.float64)
    sim = Simulator(x, volume, MaterialSpec("elastic", {"youngs_modulus": moduli}), grid, frame_dt=1e-3, device=device)
    host, host_cpu, wall = _time_substeps(device, sim, substeps)
    us = 1e6 / substeps / POPULATION
    single = sizes[str(x.shape[0])]
    result = {
        "members": POPULATION,
        "particles_per_member": x.shape[0],
        "host_us_per_member_substep": host * us,
        "host_cpu_us_per_member_substep": host_cpu * us,
        "wall_us_per_member_substep": wall * us,
        "host_share_of_single": host * us / single["host_us_per_substep"],
        "host_cpu_share_of_single": host_cpu * us / single["host_cpu_us_per_substep"],
    }
    click.echo(
        f"a population of {POPULATION} x {x.shape[0]:,d} particles: {host * us:6.1f} us of host time a "
        f"member-substep ({host_cpu * us:5.1f} us on its thread), {result['host_share_of_single']:.3f} "
        f"({result['host_cpu_share_of_single']:.3f}) of a single run's; {wall * us:7.1f} us of wall time"
    )
    return result
