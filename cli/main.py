"""Root ``clflow`` command: global options and lazy registration of subcommands."""

from __future__ import annotations

import importlib
import logging
import os
import sys
import warnings
from importlib.metadata import entry_points

import click

from clflow import __version__
from clflow_cli.options import OutputPath

# torch's OpenMP threads spin for a while after every parallel torch op, taking the cores
# from the OpenCL CPU device's worker threads (what it costs: docs/architecture.md, "Runtime").
# Let them sleep unless the user chose otherwise; libgomp reads this when torch loads,
# which is after this line (the commands import torch lazily).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# name -> "module:attribute" of clflow's own subcommands. Modules here import only click at
# module level; heavy imports (torch, pyopencl, cv2) happen inside the command functions.
BUILTIN_COMMANDS: dict[str, str] = {
    "bench": "clflow_cli.bench:bench",
    "devices": "clflow_cli.devices:devices",
    "query": "clflow_cli.query:query",
    "render": "clflow_cli.render:render",
    "flow": "clflow_cli.flow:flow",
    "simulate": "clflow_cli.simulate:simulate",
    "optimize": "clflow_cli.optimize:optimize",
    "render4d": "clflow_cli.render4d:render4d",
    "reconstruct": "clflow_cli.reconstruct:reconstruct",
    "pacnerf": "clflow_cli.pacnerf:pacnerf",
    "demo": "clflow_cli.demo:demo",
    "eval": "clflow_cli.eval:eval_group",
    "generate": "clflow_cli.generate:generate",
    "sweep": "clflow_cli.sweep:sweep",
    "view": "clflow_cli.view:view",
}

PLUGIN_GROUP = "clflow.commands"


INTERRUPTED_EXIT_CODE = 130  # 128 + SIGINT, what shells report for a command ended by Ctrl-C
TERMINATED_EXIT_CODE = 143  # 128 + SIGTERM, what schedulers, Ray and `kill` send


class Interrupted(click.ClickException):
    """Ctrl-C: a one-line message (e.g. how to resume) and exit code 130."""

    exit_code = INTERRUPTED_EXIT_CODE


class Terminated(Interrupted):
    """SIGTERM, handled as Ctrl-C is (the same cleanup and message), with exit code 143."""

    exit_code = TERMINATED_EXIT_CODE


class _SigtermAsInterrupt:
    """While installed, SIGTERM raises KeyboardInterrupt in the main thread, so a terminated
    command cleans up and says how to resume exactly as after Ctrl-C; ``received`` tells the
    two apart for the exit code."""

    received = False

    @classmethod
    def install(cls) -> None:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, cls._handle)

    @classmethod
    def _handle(cls, signum, frame) -> None:
        cls.received = True
        raise KeyboardInterrupt


class LazyGroup(click.Group):
    """A click group that imports a subcommand's module only when it is needed.

    ``table`` maps command names to ``"module:attribute"``; ``plugin_group`` names the
    entry-point group third-party packages register extra commands in (None: no plugins).
    """

    table: dict[str, str] = BUILTIN_COMMANDS
    plugin_group: str | None = PLUGIN_GROUP

    def _plugins(self, **select):
        return entry_points(group=self.plugin_group, **select) if self.plugin_group else []

    def list_commands(self, ctx: click.Context) -> list[str]:
        names = set(self.table) | {ep.name for ep in self._plugins()}
        return sorted(names | set(super().list_commands(ctx)))

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name in self.table:
            module_name, attr = self.table[name].split(":")
            return getattr(importlib.import_module(module_name), attr)
        for ep in self._plugins(name=name):
            try:
                return ep.load()
            except Exception as exc:  # a broken plugin must not break the whole CLI (nor --help)
                return broken_command(
                    name, f"plugin command {name!r} ({ep.value}) failed to load: {type(exc).__name__}: {exc}"
                )
        return super().get_command(ctx, name)

    def make_context(self, info_name, args, parent=None, **extra) -> click.Context:
        # the root's own options (--profile PATH) are checked as they are parsed: one line too
        from clflow.errors import ClflowError

        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except ClflowError as exc:
            raise click.ClickException(str(exc)) from None

    def invoke(self, ctx: click.Context):
        # User-fixable problems (bad input, missing device, ...) end with one clear line and
        # exit code 1, and so do file-system refusals (disk full, read-only, a file where a
        # folder should be); Ctrl-C with one line and 130; anything else is a bug and keeps its traceback.
        from clflow.errors import ClflowError
        from clflow.fileio import FILE_SYSTEM_ERRNOS, describe_os_error

        try:
            return super().invoke(ctx)
        except click.UsageError as exc:  # a wrong command line: one line, exit 2, where help is
            if exc.ctx is None:
                raise
            hint = f" (see '{exc.ctx.command_path} -h')"
            raise click.UsageError(exc.format_message() + hint) from None
        except ClflowError as exc:
            raise click.ClickException(str(exc)) from None
        except OSError as exc:
            if exc.errno not in FILE_SYSTEM_ERRNOS:
                raise
            raise click.ClickException(describe_os_error(exc)) from None
        except KeyboardInterrupt as exc:  # its message, if any, says what was saved and how to resume
            raise (Terminated if _SigtermAsInterrupt.received else Interrupted)(str(exc) or "interrupted") from None


def broken_command(name: str, message: str) -> click.Command:
    """A placeholder for a command that cannot be loaded: listed by --help as broken, and
    running it prints ``message`` and exits 1 (as rasterio's click-plugins do)."""

    def fail(**_):
        raise click.ClickException(message)

    return click.Command(
        name,
        callback=fail,
        help=message,
        short_help="(broken plugin: run it to see why)",
        context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
        add_help_option=False,
    )


class CliContext:
    """Shared state handed to subcommands as ``ctx.obj``."""

    def __init__(self, device: str | None, verbosity: int):
        self.device_spec = device
        self.verbosity = verbosity

    def device(self):
        """The selected OpenCL device (``--device`` / ``CLFLOW_DEVICE`` / default)."""
        from clflow.runtime import get_device

        return get_device(self.device_spec)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="clflow")
@click.option(
    "--device",
    "-d",
    metavar="NAME",
    envvar="CLFLOW_DEVICE",
    help="OpenCL device: a case-insensitive substring of the device name, or "
    "'platform:device'. Default: $CLFLOW_DEVICE, else the first GPU, else PoCL's CPU device.",
)  # fmt: skip
@click.option("--bridge", type=click.Choice(["auto", "copy"]), default=None, envvar="CLFLOW_BRIDGE",
              help="How tensors reach the device: 'auto' shares host memory where the device does (CPUs), "
              "'copy' keeps separate device buffers and copies, as on a discrete GPU (to test that path on "
              "a CPU). Default: $CLFLOW_BRIDGE, else auto.")  # fmt: skip
@click.option("--kernels", type=click.Choice(["auto", "cpu", "gpu"]), default=None, envvar="CLFLOW_KERNELS",
              help="The kernels' shapes (docs/gpu.md): 'cpu' (a few work-items streaming through blocks), 'gpu' "
              "(work-groups cooperating in local memory), 'auto' by the device's type. Default: $CLFLOW_KERNELS, "
              "else auto.")  # fmt: skip
@click.option("--profile", "profile_path", type=OutputPath(file=True), default=None, metavar="PATH",
              help="Record every kernel launch of the command (OpenCL profiling events): a table of device time "
              "per kernel on stderr at the end, and as JSON at PATH.")  # fmt: skip
@click.option("--wait", is_flag=True, envvar="CLFLOW_WAIT",
              help="When another clflow run is writing the output folder, wait for it to finish instead of "
              "refusing. Default: $CLFLOW_WAIT, else refuse.")  # fmt: skip
@click.option("-v", "--verbose", count=True,
              help="More log output (repeatable; -vv adds pyopencl's per-kernel build messages).")  # fmt: skip
@click.option("-q", "--quiet", count=True, help="Less log output (repeatable).")
@click.pass_context
def cli(
    ctx: click.Context,
    device: str | None,
    bridge: str | None,
    kernels: str | None,
    profile_path: str | None,
    wait: bool,
    verbose: int,
    quiet: int,
) -> None:
    """clflow: physically simulated 4D scenes from 3D Gaussian splats and a guidance video.

    OpenCL MLS-MPM and Gaussian-splat kernels (forward and adjoint) behind a PyTorch API.
    """
    verbosity = verbose - quiet
    level = {-2: logging.ERROR, -1: logging.WARNING, 0: logging.INFO}.get(max(-2, min(verbosity, 1)), logging.DEBUG)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    # torch's own INFO lines (e.g. "FakeTensor cache stats" at exit after a Ctrl-C during its
    # import, before torch set its loggers' levels) are not clflow's progress
    logging.getLogger("torch").setLevel(max(level, logging.WARNING))
    _fold_kernel_builds(verbosity < 2)
    warnings.showwarning = _log_warning
    ctx.obj = CliContext(device, verbosity)
    _SigtermAsInterrupt.install()
    if device:
        from clflow.runtime import set_default_device

        set_default_device(device)
    if bridge:
        from clflow.runtime import set_bridge_mode

        set_bridge_mode(bridge)
    if wait:
        from clflow.fileio import wait_for_writers

        wait_for_writers(True)
    if kernels:
        from clflow.runtime.plan import KERNELS_ENV

        os.environ[KERNELS_ENV] = kernels  # read by clflow.runtime.plan, here and in worker processes
    if profile_path and ctx.invoked_subcommand:
        _profile_command(ctx, profile_path)


def _profile_command(ctx: click.Context, path: str) -> None:
    """Profile the device's kernels from here to the end of the command; then print the
    table to stderr and write the summary, with the environment, as JSON at ``path``."""
    device = ctx.obj.device()
    device.start_profile()

    def report() -> None:
        from clflow.benchmark import write_record
        from clflow.runtime.profile import format_profile

        summary = device.stop_profile()
        click.echo(format_profile(summary), err=True)
        write_record(path, "profile", {"command": " ".join(sys.argv[1:])}, summary)

    ctx.call_on_close(report)


class _FoldKernelBuilds(logging.Filter):
    """Drops pyopencl's "build program: ..." records (one per program, cached or not): a
    build that really compiles says so itself (clflow.runtime.devices, "compiled kernels")."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("build program")


def _fold_kernel_builds(fold: bool) -> None:
    """Fold pyopencl's build messages (``fold``), or let them through as they are (-vv)."""
    loggers = [logging.getLogger(name) for name in ("pyopencl", "pyopencl.cache")]
    for logger in loggers:
        for old in [f for f in logger.filters if isinstance(f, _FoldKernelBuilds)]:
            logger.removeFilter(old)
    if fold:
        for logger in loggers:
            logger.addFilter(_FoldKernelBuilds())


def _log_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Python warnings (e.g. clflow.mpm's StabilityWarning) as one log line each."""
    logging.getLogger("clflow").warning("%s: %s", category.__name__, message)


def main() -> None:  # pragma: no cover - thin wrapper for `python -m clflow_cli`
    cli()
