"""``clflow bench raster``: forward and backward time of the splat rasteriser."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option, double_option


def make_scene(n: int, width: int, height: int, seed: int = 0, dtype=None):
    """A synthetic scene in front of an OpenCV camera at the origin looking down +z.

    Means uniform in a 2 m cube centred 4 m away; log-uniform scales 5-30 mm (a few pixels
    to a few tens of pixels on screen, as in trained 3DGS scenes); opacities 0.1-0.9.
    Returns the positional and keyword arguments of ``rasterize_gaussians``.
    """
    import torch

    dtype = dtype or torch.float32
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) * 2 - 1) + torch.tensor([0.0, 0.0, 4.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(
        torch.empty(n, 3, dtype=dtype).uniform_(
            float(torch.log(torch.tensor(0.005))), float(torch.log(torch.tensor(0.03))), generator=g
        )
    )
    opacities = torch.rand(n, generator=g, dtype=dtype) * 0.8 + 0.1
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    viewmat = torch.eye(4, dtype=dtype)
    focal = float(width)  # fx = width: a 53 degree horizontal field of view
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=dtype)
    return (means, quats, scales, opacities, colors, viewmat, K, width, height), {}


@bench_command("raster")
@count_option("-n", "--gaussians", default=100_000, help="Number of Gaussians.")
@count_option("--size", default=512, help="Image width and height (pixels).")
@count_option('--repeat', default=10, help="Timed runs (the median is printed).")  # fmt: skip
@double_option
@click.pass_obj
def raster(obj, gaussians: int, size: int, repeat: int, double: bool) -> dict:
    """Forward and backward time for N Gaussians at SIZE x SIZE, RGB + depth."""
    import os

    import torch

    from clflow.benchmark import Stopwatch
    from clflow.runtime import get_device, set_default_device
    from clflow.runtime.devices import Transfers
    from clflow.splat.ops import rasterize_gaussians

    if obj is not None and obj.device_spec:
        set_default_device(obj.device_spec)
    device = get_device()
    dtype = torch.float64 if double else torch.float32
    args, kwargs = make_scene(gaussians, size, size, dtype=dtype)
    leaves = [a.requires_grad_() for a in args[:5]]
    forward, backward = Stopwatch(), Stopwatch()
    copied = {"forward": Transfers(), "backward": Transfers()}  # over the timed calls
    for run in range(repeat + 1):  # the first run builds the kernels and is not timed
        for leaf in leaves:
            leaf.grad = None
        mark = device.transfers.mark()
        with forward:
            image, alpha, depth, meta = rasterize_gaussians(*args, **kwargs)
        between = device.transfers.mark()
        loss = image.sum() + alpha.sum() + depth.sum()
        with backward:
            loss.backward()
        if run:
            for name, moved in (("forward", between.since(mark)), ("backward", device.transfers.since(between))):
                copied[name].count(moved.to_device, moved.to_host)
    visible = int((meta["radii"] > 0).sum())
    memory = "separate memory" if not device.zero_copy else "shared memory"
    click.echo(f"device: {device.info.label} ({memory})")
    click.echo(f"raster: {gaussians} Gaussians ({visible} visible), {size}x{size}, RGB + depth, {dtype}")
    click.echo(
        f"  tile entries: {meta['num_tile_entries']} ({meta['tile_list_bytes'] / 2**20:.1f} MiB of tile lists, "
        f"{meta['entry_record_bytes'] / 2**20:.1f} MiB of compositing records)"
    )
    results = {"visible": visible, "tile_entries": int(meta["num_tile_entries"])}
    for name, watch in (("forward", forward), ("backward", backward)):
        timing = watch.timing(skip=1)
        to_device, to_host = copied[name].to_device / repeat, copied[name].to_host / repeat
        results[name] = {**timing.record(), "bytes_to_device_per_call": to_device, "bytes_to_host_per_call": to_host}
        click.echo(
            f"  {name + ':':9} {1e3 * timing.median_wall:8.1f} ms wall, {1e3 * timing.median_cpu:8.1f} ms CPU "
            f"(medians of {repeat}); copied per call: {to_device / 2**20:.2f} MiB to the device, "
            f"{to_host / 2**20:.2f} MiB to the host"
        )
    click.echo(f"  load average: {timing.load_after} on {os.cpu_count()} cores (wall times grow with it)")
    return results
