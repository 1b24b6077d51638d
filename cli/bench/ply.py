"""``clflow bench ply``: 3DGS PLY write / read throughput and point-cloud initialisation."""

import click

from clflow_cli.bench import bench_command
from clflow_cli.options import count_option


@bench_command("ply")
@count_option('--gaussians', 'count', default=1_000_000, help="Number of Gaussians in the file.")  # fmt: skip
@click.option("--sh-degree", type=click.IntRange(0, 3), default=3, show_default=True)
@click.option("--points", type=click.IntRange(min=0), default=100_000, show_default=True,
              help="Points for Gaussians.from_points (3-NN scales); 0 skips it.")  # fmt: skip
@count_option('--repeat', default=3, help="Timed runs (median reported).")  # fmt: skip
def ply(count: int, sh_degree: int, points: int, repeat: int) -> dict:
    """Median time of save_ply and load_ply (binary float32, INRIA layout) and of from_points."""
    import tempfile
    from pathlib import Path

    import torch

    from clflow.benchmark import measure
    from clflow.splat import Gaussians, load_ply, save_ply

    gen = torch.Generator().manual_seed(0)
    g = Gaussians(
        means=torch.randn(count, 3, generator=gen),
        quats=torch.randn(count, 4, generator=gen),
        log_scales=torch.randn(count, 3, generator=gen) - 4,
        opacity_logits=torch.randn(count, generator=gen),
        sh=torch.randn(count, (sh_degree + 1) ** 2, 3, generator=gen),
    )

    def median_seconds(fn) -> float:
        return measure(fn, repeat).median_wall  # after a warm-up: imports, page cache

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "bench.ply"
        save_seconds = median_seconds(lambda: save_ply(path, g))
        load_seconds = median_seconds(lambda: load_ply(path))
        mib = path.stat().st_size / 2**20
    click.echo(f"PLY, {count} Gaussians of SH degree {sh_degree} ({mib:.0f} MiB), median of {repeat}:")
    click.echo(f"  save_ply  {save_seconds:6.2f} s  ({mib / save_seconds:5.0f} MiB/s)")
    click.echo(f"  load_ply  {load_seconds:6.2f} s  ({mib / load_seconds:5.0f} MiB/s)")
    if points:
        cloud = torch.randn(points, 3, generator=gen)
        seconds = median_seconds(lambda: Gaussians.from_points(cloud))
        click.echo(f"  from_points ({points} points, exact 3-NN scales)  {seconds:6.2f} s")
    return {
        "file_mib": mib,
        "save_s": save_seconds,
        "load_s": load_seconds,
        "from_points_s": seconds if points else None,
    }
