"""``clflow eval ...``: accuracy benchmarks (figures recorded in docs/benchmarks.md)."""

import click

from clflow_cli.main import LazyGroup

# name -> "module:command" of each evaluation; imported only when it runs.
EVALUATIONS: dict[str, str] = {
    "sysid": "clflow_cli.eval_sysid:sysid",
}


class EvalGroup(LazyGroup):
    table = EVALUATIONS
    plugin_group = None


@click.group("eval", cls=EvalGroup)
def eval_group() -> None:
    """Measure how accurately clflow identifies what it is asked to (ground truth known)."""
