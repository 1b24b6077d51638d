"""A sweep's SPEC (YAML): its runs of ``simulate``, ``optimize`` or an ``eval sysid`` case,
each checked (its config loaded with its overrides) before any work."""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from clflow.errors import InputError

COMMANDS = ("simulate", "optimize", "sysid")
SPEC_KEYS = ("command", "options", "set", "configs", "base", "grid", "overrides", "cases", "sysid", "runs", "timeout")
RUN_KEYS = ("name", "command", "config", "set", "options", "case", "timeout")
#: options of each command (as in its CLI), with a check of the value
OPTIONS: dict[str, dict[str, str]] = {
    "simulate": {"preview": "one of mp4, png, none", "params": "a params.json file", "max_output_gb": "a number > 0"},
    "optimize": {"iterations": "a whole number >= 1"},
    "sysid": {},
}
SYSID_KEYS = ("quick", "iterations", "truth_scale", "noise", "codec", "seed", "views")
FINISHED = ("ok", "failed", "timeout", "killed")  # statuses a run ends with


@dataclass(frozen=True)
class Run:
    """One run of a sweep: a command with its config (absolute path) and overrides, or a sysid case."""

    command: str
    config: str | None = None
    overrides: tuple[str, ...] = ()  # "key.sub=value" (value as JSON, which YAML reads)
    options: dict = field(default_factory=dict, hash=False)
    case: str | None = None
    sysid: dict | None = field(default=None, hash=False)  # sysid settings
    timeout: float | None = None  # seconds; None: the sweep's --timeout
    label: str | None = None  # the spec's name for it

    def params(self) -> dict:
        """What the run depends on (JSON data; the folder name's hash is made from it)."""
        out: dict[str, Any] = {"command": self.command}
        if self.config is not None:
            out["config"] = self.config
        if self.overrides:
            out["set"] = list(self.overrides)
        if self.options:
            out["options"] = dict(sorted(self.options.items()))
        if self.case is not None:
            out.update(case=self.case, sysid=self.sysid)
        return out

    @property
    def name(self) -> str:
        """A stable folder name: readable parts of the parameters and a hash of all of them."""
        parts = [self.command, self.label or self.case or Path(self.config or "run").stem]
        slug = re.sub(r"[^A-Za-z0-9._=+-]+", "_", "-".join(parts)).strip("_")[:80]
        return f"{slug}-{_digest(self.params())[:8]}"


def inputs_of(run: Run) -> dict[str, str]:
    """What ``run`` reads, each by 16 hex digits of a SHA-256 of its content: its parameters
    (``run``), its config as loaded with its overrides (under the config file's name: the
    resolved values, paths as they are written, ``output`` left out: the sweep chooses it),
    and each file or folder that config or a ``params`` option names, by what it holds
    (clflow.fileio.content_digest; under its path from the config's folder). A run whose
    earlier record has other inputs is run again (clflow.sweep.study)."""
    from dataclasses import asdict

    from clflow.fileio import content_digest
    from clflow.scene.config import load_config

    parts = {"run": _digest(run.params())}
    files, home = [], None
    if run.config is not None:
        config = Path(run.config)
        fields = asdict(load_config(config, run.overrides))
        fields.pop("output", None)
        parts[config.name] = _digest(fields)
        files, home = [p for p in _paths(fields) if p != config], config.parent
    if "params" in run.options:
        files.append(Path(run.options["params"]))
    for path in sorted(set(files)):
        inside = home is not None and path.is_relative_to(home)
        parts[path.relative_to(home).as_posix() if inside else str(path)] = content_digest(path)[:16]
    return parts


def _digest(value: Any) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _paths(value: Any) -> list[Path]:
    """Every Path in ``value`` (dicts, lists and tuples of them: a config as asdict gives it)."""
    if isinstance(value, Path):
        return [value]
    if isinstance(value, dict):
        value = list(value.values())
    if isinstance(value, (list, tuple)):
        return [p for v in value for p in _paths(v)]
    return []


@dataclass(frozen=True)
class Spec:
    source: Path
    runs: tuple[Run, ...]


def load_spec(path: str | os.PathLike) -> Spec:
    """Read and fully validate a sweep SPEC; any problem is one InputError line."""
    from clflow.scene.config.files import read_data_file

    path = Path(path)
    return parse_spec(read_data_file(path, "sweep spec"), path)


def parse_spec(data: Any, path: Path) -> Spec:
    """Validate parsed SPEC ``data`` (from file ``path``; relative paths are from its folder)."""
    r = _SpecReader(path)
    top = r.mapping(data, "", SPEC_KEYS)
    if not top:
        raise r.fail("", "the spec is empty; it needs configs, base with grid or overrides, cases or runs")
    command = r.command_of(top.get("command", "optimize"), "command")
    spec = _Defaults(
        r,
        command,
        r.overrides(top.get("set"), "set"),
        r.options(command, top.get("options"), "options"),
        r.seconds(top.get("timeout"), "timeout"),
        r.sysid_settings(r.mapping(top.get("sysid"), "sysid", SYSID_KEYS)),
    )
    runs = _config_runs(r, top, spec) + _case_runs(r, top, spec) + _listed_runs(r, top, spec)
    if not runs:
        raise r.fail("", "no runs: give configs, base (with grid or overrides), cases or runs")
    keys = [json.dumps(run.params(), sort_keys=True) for run in runs]
    twice = sorted({run.name for run, k in zip(runs, keys) if keys.count(k) > 1})
    if twice:
        raise r.fail("", f"runs given twice (same command, config and overrides): {', '.join(twice)}")
    for run in runs:  # every config as it will run: unknown keys, bad values, missing files
        if run.config is not None:
            from clflow.scene.config import load_config

            try:
                load_config(run.config, run.overrides)
            except InputError as exc:
                raise r.fail(f"run {run.name}", str(exc)) from None
    return Spec(path, tuple(runs))


class _SpecReader:
    """Checks the values of a parsed spec from file ``path``; each error one line naming the
    file and the key."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, where: str, what: str) -> InputError:
        return InputError(f"{self.path}: {where + ': ' if where else ''}{what}")

    def mapping(self, value: Any, where: str, keys: Iterable[str] | None = None) -> dict:
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.fail(where, f"must be a mapping, got {value!r}")
        if keys is not None:
            unknown = [k for k in value if k not in keys]
            if unknown:
                raise self.fail(where, f"unknown key {unknown[0]!r}; the keys are {', '.join(keys)}")
        return value

    def items(self, value: Any, where: str) -> list:
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.fail(where, f"must be a list, got {value!r}")
        return value

    def command_of(self, value: Any, where: str) -> str:
        if value not in COMMANDS:
            raise self.fail(where, f"unknown command {value!r}; the commands are {', '.join(COMMANDS)}")
        return value

    def config_path(self, value: Any, where: str) -> str:
        """An existing config file, relative to the spec's folder, as an absolute path."""
        if not isinstance(value, str) or not value:
            raise self.fail(where, f"must be a config file path, got {value!r}")
        file = (self.path.parent / value).resolve()
        if not file.is_file():
            raise self.fail(where, f"config {value} not found (paths are relative to the spec's folder)")
        return str(file)

    def overrides(self, value: Any, where: str) -> tuple[str, ...]:
        """A mapping of dotted config keys to values as ``key=JSON`` overrides (``--set``)."""
        out = []
        for key, v in self.mapping(value, where).items():
            if not isinstance(key, str) or not re.fullmatch(r"[A-Za-z0-9_]+(\.[A-Za-z0-9_]+)*", key):
                raise self.fail(where, f"{key!r} is not a dotted config key (e.g. simulation.frames)")
            out.append(f"{key}={json.dumps(v)}")
        return tuple(out)

    def options(self, command: str, value: Any, where: str) -> dict:
        """A command's options (OPTIONS), a params file made absolute."""
        given = self.mapping(value, where, OPTIONS[command])
        for key, v in given.items():
            ok = {
                "preview": lambda: v in ("mp4", "png", "none"),
                "params": lambda: isinstance(v, str) and (self.path.parent / v).is_file(),
                "max_output_gb": lambda: isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0,
                "iterations": lambda: isinstance(v, int) and not isinstance(v, bool) and v >= 1,
            }[key]()
            if not ok:
                raise self.fail(f"{where}.{key}", f"must be {OPTIONS[command][key]}, got {v!r}")
        if "params" in given:
            given = {**given, "params": str((self.path.parent / given["params"]).resolve())}
        return dict(given)

    def seconds(self, value: Any, where: str) -> float | None:
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise self.fail(where, f"must be a number of seconds > 0, got {value!r}")
        return float(value)

    def case(self, value: Any, where: str) -> str:
        from clflow_datasets.sysid_cases import CASES

        if value not in CASES:
            raise self.fail(where, f"unknown sysid case {value!r}; the cases are {', '.join(CASES)}")
        return value

    def sysid_settings(self, given: dict) -> dict:
        """The ``sysid`` section as JSON data (checked when a run makes its Settings)."""
        checks = {
            "quick": lambda v: isinstance(v, bool),
            "iterations": lambda v: _whole(v, 1),
            "truth_scale": lambda v: _whole(v, 1),
            "seed": lambda v: _whole(v, None),
            "views": lambda v: _whole(v, 1) and v <= 4,
            "codec": lambda v: v in (None, ".mp4", ".webm", ".avi"),
            "noise": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0,
        }
        for key, value in given.items():
            if not checks[key](value):
                raise self.fail(f"sysid.{key}", f"bad value {value!r}")
        return dict(sorted(given.items()))


def _whole(v: Any, low: int | None) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and (low is None or v >= low)


@dataclass(frozen=True)
class _Defaults:
    """What the spec's top level gives every run."""

    reader: _SpecReader  # reads the rest of the spec, naming the key at fault
    command: str  # the clflow command each run is
    overrides: tuple[str, ...]  # --set KEY=VALUE, before each run's own
    options: dict  # the command's options, before each run's own
    timeout: float | None  # s a run may take; None: no limit
    sysid: dict  # the sysid settings of cases' runs

    def config_run(
        self,
        config: str,
        sets: tuple[str, ...],
        where: str,
        command: str | None = None,
        options: dict | None = None,
        timeout: float | None = None,
        label: str | None = None,
    ) -> Run:
        """A run of a config with the spec's ``set`` and then ``sets``."""
        command = command or self.command
        if command == "sysid":
            raise self.reader.fail(where, "a sysid run takes a case, not a config")
        if label is None:  # readable: the config's name and what this run sets besides the spec's set
            label = "-".join(
                [Path(config).stem] + [f"{o.split('=')[0].split('.')[-1]}={o.partition('=')[2]}" for o in sets]
            )
        return Run(
            command,
            config,
            self.overrides + sets,
            self.options if options is None else options,
            timeout=timeout or self.timeout,
            label=label,
        )


def _config_runs(r: _SpecReader, top: dict, spec: _Defaults) -> list[Run]:
    """``configs`` as they are, then ``base`` with each ``grid`` combination and ``overrides`` entry."""
    runs = [
        spec.config_run(r.config_path(config, f"configs[{i}]"), (), f"configs[{i}]")
        for i, config in enumerate(r.items(top.get("configs"), "configs"))
    ]
    grid = r.mapping(top.get("grid"), "grid")
    listed = r.items(top.get("overrides"), "overrides")
    if "base" in top:
        base = r.config_path(top["base"], "base")
        for key, values in grid.items():
            if not isinstance(values, list) or not values:
                raise r.fail(f"grid.{key}", f"must be a non-empty list of values, got {values!r}")
        keys = list(grid)
        combos = [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))] if grid else []
        combos += [r.mapping(o, f"overrides[{i}]") for i, o in enumerate(listed)]
        runs += [spec.config_run(base, r.overrides(combo, "grid"), "base") for combo in combos or [{}]]
    elif grid or listed:
        raise r.fail("grid" if grid else "overrides", "needs a base config (base: FILE)")
    return runs


def _case_runs(r: _SpecReader, top: dict, spec: _Defaults) -> list[Run]:
    """``cases``: sysid cases with the spec's sysid settings."""
    cases = r.items(top.get("cases"), "cases")
    if cases and spec.command != "sysid":
        raise r.fail("cases", f"sysid cases need command: sysid, not {spec.command}")
    return [Run("sysid", case=r.case(case, "cases"), sysid=spec.sysid, timeout=spec.timeout) for case in cases]


def _listed_runs(r: _SpecReader, top: dict, spec: _Defaults) -> list[Run]:
    """``runs``: each a command with its own config, set, options, case, name and time limit."""
    runs = []
    for i, entry in enumerate(r.items(top.get("runs"), "runs")):
        where = f"runs[{i}]"
        entry = r.mapping(entry, where, RUN_KEYS)
        command = r.command_of(entry.get("command", spec.command), f"{where}.command")
        label = entry.get("name")
        if label is not None and (not isinstance(label, str) or not re.fullmatch(r"[A-Za-z0-9._=+-]+", label)):
            raise r.fail(f"{where}.name", f"must be letters, digits and . _ = + -, got {label!r}")
        timeout = r.seconds(entry.get("timeout"), f"{where}.timeout") or spec.timeout
        options = {
            **(spec.options if command == spec.command else {}),
            **r.options(command, entry.get("options"), f"{where}.options"),
        }
        if command == "sysid":
            if "config" in entry or "set" in entry:
                raise r.fail(where, "a sysid run takes a case, not a config or set")
            case = r.case(entry.get("case"), f"{where}.case")
            runs.append(Run("sysid", case=case, sysid=spec.sysid, timeout=timeout, label=label))
            continue
        if "case" in entry:
            raise r.fail(f"{where}.case", f"only sysid runs take a case, this one is {command}")
        if "config" not in entry:
            raise r.fail(where, f"a {command} run needs a config")
        config = r.config_path(entry["config"], f"{where}.config")
        sets = r.overrides(entry.get("set"), f"{where}.set")
        runs.append(spec.config_run(config, sets, where, command, options, timeout, label))
    return runs


def sysid_settings(record: dict):
    """clflow_datasets.sysid.Settings from a spec's ``sysid`` section."""
    from clflow_datasets.sysid import Settings

    fields = {k: v for k, v in record.items() if k not in ("quick", "iterations")}
    return Settings.at(bool(record.get("quick")), record.get("iterations"), **fields)
