"""``clflow bench ...``: throughput benchmarks (figures recorded in docs/benchmarks.md)."""

import functools

import click

from clflow_cli.main import LazyGroup
from clflow_cli.options import OutputPath

# name -> "module:command" of each benchmark; imported only when it runs.
BENCHMARKS: dict[str, str] = {
    "query": "clflow_cli.bench.query:query",
    "ply": "clflow_cli.bench.ply:ply",
    "flow": "clflow_cli.bench.flow:flow",
    "raster": "clflow_cli.bench.raster:raster",
    "mpm": "clflow_cli.bench.mpm:mpm",
    "mpm-adjoint": "clflow_cli.bench.mpm_adjoint:mpm_adjoint",
    "launch": "clflow_cli.bench.launch:launch",
    "optimize": "clflow_cli.bench.optimize:optimize",
    "reconstruct": "clflow_cli.bench.reconstruct:reconstruct",
    "write": "clflow_cli.bench.write:write",
}


class BenchGroup(LazyGroup):
    table = BENCHMARKS
    plugin_group = None


@click.group(cls=BenchGroup)
def bench() -> None:
    """Measure throughput of clflow's kernels on the selected device."""


def bench_command(name: str):
    """Make ``fn`` the command ``clflow bench NAME``. ``fn`` prints its figures and returns
    them (a JSON-ready dict, timings from clflow.benchmark); ``--json PATH`` writes them with
    the command's parameters and the environment (versions, device, load); ``--profile``
    adds the kernel profile of the whole run (clflow.runtime.profile)."""

    def wrap(fn):
        @functools.wraps(fn)
        def run(*args, json_path, profile, **parameters):
            device = None
            if profile:
                from clflow.runtime import get_device

                obj = click.get_current_context().find_root().obj
                device = obj.device() if obj else get_device()
                device.start_profile()
            results = fn(*args, **parameters)
            if device is not None:
                from clflow.runtime.profile import format_profile

                results["profile"] = device.stop_profile()
                click.echo(format_profile(results["profile"]))
                parameters["profile"] = True
            if json_path:
                from clflow.benchmark import write_record

                write_record(json_path, name, parameters, results)
                click.echo(f"wrote {json_path}")

        option = click.option(
            "--json",
            "json_path",
            type=OutputPath(file=True),
            default=None,
            metavar="PATH",
            help="Also write the figures, the parameters and the environment as JSON to PATH.",
        )
        profile = click.option(
            "--profile",
            is_flag=True,
            help="Also record every kernel launch's device time (OpenCL profiling events): launches, "
            "seconds and share per kernel, host time and launches per substep; printed, and in --json.",
        )
        return click.command(name)(profile(option(run)))

    return wrap
