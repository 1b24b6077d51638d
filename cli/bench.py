"""``clflow bench ...``: throughput benchmarks (figures recorded in docs/benchmarks.md)."""

import click

from clflow_cli.main import LazyGroup

# name -> "module:command" of each benchmark; imported only when it runs.
BENCHMARKS: dict[str, str] = {
    "mpm": "clflow_cli.bench_mpm:mpm",
    "mpm-adjoint": "clflow_cli.bench_mpm_adjoint:mpm_adjoint",
}


class BenchGroup(LazyGroup):
    table = BENCHMARKS
    plugin_group = None


@click.group(cls=BenchGroup)
def bench() -> None:
    """Measure throughput of clflow's kernels on the selected device."""
