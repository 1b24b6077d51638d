"""``clflow bench ...``: throughput benchmarks (figures recorded in docs/benchmarks.md)."""

import click

from clflow_cli.main import LazyGroup

# name -> "module:command" of each benchmark; imported only when it runs.
BENCHMARKS: dict[str, str] = {
    "query": "clflow_cli.bench_query:query",
    "ply": "clflow_cli.bench_ply:ply",
    "flow": "clflow_cli.bench_flow:flow",
    "flow-bias": "clflow_cli.bench_flow_bias:flow_bias",
    "raster": "clflow_cli.bench_raster:raster",
    "mpm": "clflow_cli.bench_mpm:mpm",
    "mpm-adjoint": "clflow_cli.bench_mpm_adjoint:mpm_adjoint",
    "optimize": "clflow_cli.bench_optimize:optimize",
    "reconstruct": "clflow_cli.bench_reconstruct:reconstruct",
}


class BenchGroup(LazyGroup):
    table = BENCHMARKS
    plugin_group = None


@click.group(cls=BenchGroup)
def bench() -> None:
    """Measure throughput of clflow's kernels on the selected device."""
