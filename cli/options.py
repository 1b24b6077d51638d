"""Options shared by clflow's commands, spelled and parsed one way everywhere.

- ``-o/--out``: every command's output (a folder, or a file where the command writes one);
  the older ``--output`` and ``--output-dir`` still work but are not shown by --help.
- Numbers in one option are one word with commas: ``--box 8,8,72,56``, ``--up 0,1,0``.
- ``--set KEY.SUB=VALUE``, ``--max-substeps N``, ``--max-output-gb GB``: as the scene
  config's keys and limits.

Like every module here, this imports only click (and clflow.limits' constants): no numpy.
"""

from __future__ import annotations

import math
import re

import click

from clflow.limits import DEFAULT_MAX_OUTPUT_GB

#: Old spellings of ``--out`` that still work (hidden from --help).
OUT_ALIASES = ("--output", "--output-dir")


class LazyHelpOption(click.Option):
    """An option whose help is ``help_fn()``, called only when --help shows it (e.g. to list
    names a heavy module defines)."""

    def __init__(self, *args, help_fn, **kwargs):
        super().__init__(*args, **kwargs)
        self.help_fn = help_fn

    def get_help_record(self, ctx):
        self.help = self.help_fn()
        return super().get_help_record(ctx)


def _name(param) -> str:
    """How the command line spells ``param``: an option's longest flag, an argument's NAME."""
    if isinstance(param, click.Option):
        return next((o for o in param.opts if o.startswith("--")), param.opts[0])
    return param.human_readable_name if param else "path"


class InputFile(click.Path):
    """An input file option or argument: a missing path or a folder is the one-line error of
    a bad input (exit 1, clflow.errors.InputError), not a usage error."""

    def __init__(self, **kwargs):
        super().__init__(dir_okay=False, **kwargs)

    def fail(self, message, param=None, ctx=None):
        from clflow.errors import InputError

        raise InputError(f"{_name(param)}: {message}")


class OutputPath(click.Path):
    """An output file (``file``) or folder, checked before any work: a folder where a file is
    meant (or the reverse), a place no file can be made (read-only, /proc, no permission), or
    a file there that clflow did not write, is a one-line InputError (exit 1)."""

    def __init__(self, file: bool = False, **kwargs):
        super().__init__(dir_okay=not file, file_okay=file, **kwargs)
        self.file = file

    def convert(self, value, param, ctx):
        from clflow.fileio import check_output_file as replaces_only_clflows
        from clflow.limits import check_output, check_output_file

        if self.file:
            check_output_file(value, _name(param))
            replaces_only_clflows(value)  # a file of the user's there is not written over
        else:
            check_output(value)
        return super().convert(value, param, ctx)

    def fail(self, message, param=None, ctx=None):
        from clflow.errors import InputError

        raise InputError(f"{_name(param)}: {message}")


class FiniteFloat(click.FloatRange):
    """A number option that refuses NaN and infinities (FloatRange lets NaN through)."""

    name = "number"

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return number

    def _describe_range(self) -> str:
        """No "[x<=None]" in --help for an unbounded number."""
        return "" if self.min is None and self.max is None else super()._describe_range()


class Numbers(click.ParamType):
    """``count`` finite numbers in one word, comma-separated (``0,0,1``; a quoted
    space-separated ``"0 0 1"`` is read too), each in [low, high] of ``within`` when given.
    Converts to a tuple of floats."""

    def __init__(self, count: int, names: str | None = None, within: tuple[float, float] | None = None):
        self.count, self.names, self.within = count, names, within
        self.name = names or ",".join(["N"] * count)

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        words = [w for w in re.split(r"[,\s]+", str(value).strip()) if w]
        try:
            numbers = tuple(float(w) for w in words)
        except ValueError:
            numbers = ()
        if len(numbers) != self.count or not all(math.isfinite(v) for v in numbers):
            what = f"{self.count} comma-separated finite numbers"
            what = f"{self.names.lower()} ({what})" if self.names else what
            hint = f"; write them as one word with commas, e.g. {self.name}" if len(words) == 1 else ""
            self.fail(f"expected {what}, got {value!r}{hint}", param, ctx)
        if self.within and not all(self.within[0] <= v <= self.within[1] for v in numbers):
            self.fail(f"{value!r}: each number must be in [{self.within[0]:g}, {self.within[1]:g}]", param, ctx)
        return numbers


class Duration(click.ParamType):
    """A wall time: seconds (``600``, ``600s``), minutes (``10min``) or hours (``1.5h``), into
    seconds."""

    name = "duration"
    UNITS = {"": 1.0, "s": 1.0, "min": 60.0, "h": 3600.0}

    def convert(self, value, param, ctx):
        if isinstance(value, (int, float)):
            return float(value)
        found = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*(s|min|h|)\s*", str(value))
        seconds = float(found.group(1)) * self.UNITS[found.group(2)] if found else math.nan
        if not math.isfinite(seconds) or seconds <= 0:
            self.fail(
                f"{value!r} is not a positive duration (seconds, or with s, min or h: 600, 10min, 1.5h)", param, ctx
            )
        return seconds


def given_options(ctx: click.Context, which) -> list[str]:
    """The options given on the command line whose parameter names ``which(name)`` picks, as
    spelled there (to refuse those that do not apply)."""
    from click.core import ParameterSource

    return [
        p.opts[0]
        for p in ctx.command.params
        if which(p.name) and ctx.get_parameter_source(p.name) is ParameterSource.COMMANDLINE
    ]


def budget_option(help: str):
    """``--budget DURATION``: the wall time that chooses the main grid, in seconds."""
    return click.option("--budget", type=Duration(), default=None, metavar="DURATION", help=help)


class AliasedOption(click.Option):
    """An option whose old spellings (``aliases``) still work but are left out of --help and
    of its error messages."""

    def __init__(self, *args, aliases: tuple[str, ...] = (), **kwargs):
        super().__init__(*args, **kwargs)
        self.aliases = tuple(aliases)

    def _shown(self, method, *args):
        opts = self.opts
        self.opts = [o for o in opts if o not in self.aliases]
        try:
            return method(*args)
        finally:
            self.opts = opts

    def get_help_record(self, ctx):
        return self._shown(super().get_help_record, ctx)

    def get_error_hint(self, ctx):
        return self._shown(super().get_error_hint, ctx)


def aliased_option(*decls: str, aliases: tuple[str, ...], **kwargs):
    """``click.option(*decls, *aliases, ...)`` with the aliases hidden (:class:`AliasedOption`);
    ``decls`` must name the parameter (its last, non-dash word)."""
    return click.option(*decls[:-1], *aliases, decls[-1], cls=AliasedOption, aliases=aliases, **kwargs)


def out_option(name: str, help: str, *, file: bool = False, aliases: tuple[str, ...] = OUT_ALIASES, **kwargs):
    """``-o/--out`` into parameter ``name``: a folder, or a file with ``file``; the old spellings
    ``aliases`` still work."""
    return aliased_option(
        "-o", "--out", name, aliases=aliases, type=kwargs.pop("type", OutputPath(file)), help=help, **kwargs
    )


max_output_option = click.option(
    "--max-output-gb",
    type=click.FloatRange(min=0, min_open=True),
    default=DEFAULT_MAX_OUTPUT_GB,
    show_default=True,
    help="Refuse, before any work, a run whose predicted output (an uncompressed upper bound) exceeds this many GB.",
)


#: ``--double``: compute in float64 instead of float32 (the benchmarks).
double_option = click.option("--double", is_flag=True, help="float64 instead of float32.")


def count_option(*decls: str, default: int | None = None, help: str | None = None):
    """A whole-number option of at least 1 (particles, frames, repeats), its default shown."""
    return click.option(
        *decls, type=click.IntRange(min=1), default=default, show_default=default is not None, help=help
    )


def set_option(help: str):
    """``--set KEY.SUB=VALUE`` (repeatable) into ``overrides``: config keys, values read as YAML."""
    return click.option("--set", "overrides", multiple=True, metavar="KEY.SUB=VALUE", help=help)


def max_substeps_option(help: str):
    """``--max-substeps N``: refuse a run needing more substeps per frame."""
    return click.option("--max-substeps", type=click.IntRange(min=1), default=None, help=help)


def pixel_box_option(help: str = "Pixel box around the object (x right, y down, x1/y1 exclusive)."):
    """``--box X0,Y0,X1,Y1`` in pixels, into ``box`` (a 4-tuple or None)."""
    return click.option("--box", type=Numbers(4, "X0,Y0,X1,Y1"), default=None, help=help)


__all__ = [
    "AliasedOption",
    "Duration",
    "FiniteFloat",
    "InputFile",
    "LazyHelpOption",
    "OutputPath",
    "Numbers",
    "OUT_ALIASES",
    "aliased_option",
    "budget_option",
    "given_options",
    "double_option",
    "max_output_option",
    "max_substeps_option",
    "out_option",
    "pixel_box_option",
    "set_option",
]
