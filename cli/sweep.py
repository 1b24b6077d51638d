"""``clflow sweep``: many simulate / optimize / sysid runs of a SPEC, on Ray or in-process (clflow.sweep)."""

from __future__ import annotations

import sys

import click

from clflow_cli.main import Interrupted
from clflow_cli.options import InputFile, out_option


def parse_resources(items: tuple[str, ...]) -> dict[str, float]:
    """``NAME=AMOUNT`` options as Ray resources (CPU and GPU included)."""
    out = {}
    for item in items:
        name, sep, amount = item.partition("=")
        try:
            value = float(amount)
        except ValueError:
            value = -1.0
        if not sep or not name.strip() or not value > 0 or value != value or value == float("inf"):
            raise click.BadParameter(f"expected NAME=AMOUNT with an amount > 0, got {item!r}", param_hint="--resources")
        out[name.strip()] = value
    return out


ray_options = [
    click.option(
        "--address",
        default=None,
        metavar="ray://HOST:PORT|auto",
        help="Join this Ray cluster instead of starting a local one (auto: the one `ray start` runs here).",
    ),
    click.option(
        "--cpus-per-task",
        type=click.IntRange(min=1),
        default=1,
        show_default=True,
        help="CPUs each task takes; its OpenCL CPU driver and torch get as many threads.",
    ),
    click.option(
        "--resources",
        "resources",
        multiple=True,
        metavar="NAME=AMOUNT",
        help="Ray resources each task needs, e.g. GPU=1 or memory_gb=4 (repeatable).",
    ),
]


def with_ray_options(f):
    for option in reversed(ray_options):
        f = option(f)
    return f


@click.command("sweep")
@click.argument("spec", type=InputFile())
@out_option("output", "Results folder: sweep.json, sweep.md and runs/NAME/ (result.json, run.log, outputs).",
            required=True)  # fmt: skip
@click.option("--serial", is_flag=True, help="Run the spec here, one run after another, without Ray.")
@with_ray_options
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True), default=None, metavar="SECONDS",
              help="Stop a run that takes longer and record it as timed out (a spec's timeout: overrides).")  # fmt: skip
@click.option("--retry-failed", is_flag=True, help="Run again the runs that failed, timed out or were killed earlier.")
@click.pass_context
def sweep(ctx, spec, output, serial, resources, **options):
    """Run every run of SPEC (YAML: scene configs, a base config with a grid or list of --set
    overrides, sysid cases; docs/sweep.md), each in its own folder under OUT, as Ray tasks
    on this machine's cores (or a cluster: --address), and merge them into OUT/sweep.json
    and sweep.md as they finish.

    A run that fails, is killed or times out is recorded with its reason and the others go
    on. Run the same command again to continue: finished runs are skipped unless their
    inputs (config, the files it names) changed since."""
    from pathlib import Path

    from clflow.parallel import require_ray
    from clflow.sweep import load_spec
    from clflow.sweep import sweep as run_sweep

    if serial and (options["address"] or resources):
        raise click.UsageError("--serial runs in this process: drop --address and --resources")
    needs = parse_resources(resources)
    parsed = load_spec(spec)  # all of it checked before any work
    if not serial:
        require_ray()
    out = Path(output)
    echo = lambda line: click.echo(line, err=True)  # noqa: E731
    click.echo(f"{len(parsed.runs)} runs{' (serial)' if serial else ''}; results in {out}", err=True)
    try:
        device = ctx.obj.device_spec if ctx.obj else None
        # the other options are the sweep's keywords (address, cpus_per_task, timeout, retry_failed)
        summary = run_sweep(parsed, out, serial=serial, resources=needs, device=device, echo=echo, **options)
    except KeyboardInterrupt:
        raise Interrupted(
            f"interrupted; finished runs are kept in {out / 'sweep.json'}; run the same command again to continue"
        ) from None
    runs = summary["runs"].values()
    bad = [r["name"] for r in runs if r["status"] != "ok"]
    click.echo(f"{len(runs) - len(bad)} of {len(runs)} runs ok; summary in {out / 'sweep.md'}")
    if bad:
        click.echo(
            f"not ok: {', '.join(bad)} (reasons in {out / 'sweep.md'}; --retry-failed runs them again)", err=True
        )
        sys.exit(1)
