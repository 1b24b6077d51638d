"""Reading a parsed config: each key checked for its type and range, errors naming the file
and the dotted key."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

from clflow.errors import InputError
from clflow.scene.config.keys import REQUIRED, Key, field_keys

_DEFAULT = object()

#: The largest integer a config takes (int64's): no count or index goes beyond it, and far
#: beyond it a float cannot hold one either (an OverflowError).
MAX_INTEGER = 2**63 - 1


def interval(low: float | None, high: float | None, strict_low: bool = False) -> str:
    """The allowed values as the messages say them: ``>= 0``, ``<= 1``, ``in (0, 1000]``."""

    def shown(v: float) -> str:
        return str(v) if isinstance(v, int) else f"{v:g}"

    if high is None:
        return f"{'>' if strict_low else '>='} {shown(low)}"
    if low is None:
        return f"<= {shown(high)}"
    return f"in {'(' if strict_low else '['}{shown(low)}, {shown(high)}]"


class Reader:
    """Walks a parsed config with the dotted path of each key for error messages."""

    def __init__(self, source: str, base: Path):
        self.source = source
        self.base = base

    def fail(self, path: str, message: str) -> InputError:
        return InputError(f"{self.source}: {path}: {message}" if path else f"{self.source}: {message}")

    def no_huge_integers(self, data: Any, path: str = "") -> None:
        """Refuse an integer beyond +-MAX_INTEGER anywhere in ``data``, before a key's check
        turns it into a float."""
        if isinstance(data, dict):
            for key, value in data.items():
                self.no_huge_integers(value, f"{path}.{key}" if path else str(key))
        elif isinstance(data, list):
            for i, value in enumerate(data):
                self.no_huge_integers(value, f"{path}[{i}]")
        elif isinstance(data, int) and not isinstance(data, bool) and abs(data) > MAX_INTEGER:
            raise self.fail(path, f"an integer of {len(str(abs(data)))} digits is beyond any value a config takes")

    def section(self, data: Any, path: str, known: tuple[str, ...]) -> dict:
        data = self.mapping(data, path)
        unknown = [k for k in data if k not in known]
        if unknown:
            raise self.fail(
                f"{path}.{unknown[0]}" if path else str(unknown[0]), f"unknown key; known keys here: {', '.join(known)}"
            )
        return data

    def mapping(self, data: Any, path: str) -> dict:
        """A mapping whose keys are checked elsewhere."""
        if data is None:
            return {}
        if not isinstance(data, dict):
            raise self.fail(path, f"must be a mapping of keys to values, got {type(data).__name__}")
        return data

    def _get(self, data: dict, key: str, path: str, default: Any) -> tuple[str, Any]:
        """(dotted key, value), value _DEFAULT when absent and a default exists."""
        where = f"{path}.{key}" if path else key
        if key not in data or data[key] is None:
            if default is None:
                raise self.fail(where, "is required")
            return where, _DEFAULT
        return where, data[key]

    def number(
        self,
        data: dict,
        key: str,
        path: str,
        default: float | None = None,
        *,
        low: float | None = None,
        high: float | None = None,
        strict_low: bool = False,
    ) -> float:
        """A finite number in [low, high] ((low, high] with ``strict_low``); either end may be open."""
        where, value = self._get(data, key, path, default)
        if value is _DEFAULT:
            return default
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(where, f"must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.fail(where, f"must be finite, got {value}")
        if (low is not None and (value < low or (strict_low and value == low))) or (high is not None and value > high):
            raise self.fail(where, f"must be {interval(low, high, strict_low)}, got {value:g}")
        return value

    def integer(
        self, data: dict, key: str, path: str, default: int | None = None, *, low: int = 0, high: int | None = None
    ) -> int:
        where, value = self._get(data, key, path, default)
        if value is _DEFAULT:
            return default
        if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value > high):
            raise self.fail(where, f"must be an integer {interval(low, high)}, got {value!r}")
        return value

    def vec3(
        self, data: dict, key: str, path: str, default: tuple | None = None, *, limit: float | None = None
    ) -> tuple[float, float, float]:
        """3 finite numbers, each within +-``limit`` when given."""
        where, value = self._get(data, key, path, default)
        if value is _DEFAULT:
            return default
        if (
            not isinstance(value, (list, tuple))
            or len(value) != 3
            or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in value)
        ):
            raise self.fail(where, f"must be a list of 3 finite numbers, got {value!r}")
        if limit is not None and not all(abs(c) <= limit for c in value):
            raise self.fail(where, f"must be 3 numbers {interval(-limit, limit)}, got {list(value)}")
        return tuple(float(c) for c in value)

    def choice(self, data: dict, key: str, path: str, options: tuple[str, ...], default: str | None = None) -> str:
        where = f"{path}.{key}" if path else key
        value = data.get(key)
        if value is None:
            value = default
        if value is None:
            raise self.fail(where, "is required")
        if value not in options:
            raise self.fail(where, f"must be one of {', '.join(options)}, got {value!r}")
        return value

    def file(self, data: dict, key: str, path: str, required: bool = True, folder_ok: bool = False) -> Path | None:
        where = f"{path}.{key}" if path else key
        value = data.get(key)
        if value is None:
            if required:
                raise self.fail(where, "is required (a file path, relative to the config file)")
            return None
        if not isinstance(value, str) or not value:
            raise self.fail(where, f"must be a file path, got {value!r}")
        resolved = (self.base / value).resolve()
        if not (resolved.is_file() or (folder_ok and resolved.is_dir())):
            raise self.fail(where, f"{'file or folder' if folder_ok else 'file'} not found: {resolved}")
        return resolved

    def items(self, data: dict, key: str, path: str) -> list:
        value = data.get(key, [])
        if value is None:
            return []
        if not isinstance(value, list):
            raise self.fail(f"{path}.{key}" if path else key, f"must be a list, got {type(value).__name__}")
        return value

    def read(self, data: dict, path: str, key: Key) -> Any:
        """The value of ``key`` in ``data`` (its section's, at ``path``), checked as the key
        declares it: kind, range, default (an optional key's absence: None)."""
        if key.default is None and data.get(key.name) is None:
            return None
        default = None if key.default is REQUIRED else key.default
        if key.kind == "integer":
            return self.integer(data, key.name, path, default, low=key.low or 0, high=key.high)
        if key.kind == "number":
            return self.number(data, key.name, path, default, low=key.low, high=key.high, strict_low=key.strict_low)
        if key.kind == "vec3":
            return self.vec3(data, key.name, path, default, limit=key.high)
        if key.kind == "choice":
            return self.choice(data, key.name, path, key.choices, default)
        if key.kind == "file":
            return self.file(data, key.name, path, required=key.required, folder_ok=key.folder_ok)
        where = f"{path}.{key.name}" if path else key.name
        if key.kind == "flag":  # null is no default here: true or false only
            value = data.get(key.name, default)
            if not isinstance(value, bool):
                raise self.fail(where, f"must be true or false, got {value!r}")
            return value
        if key.kind == "text":
            value = data.get(key.name)
            if value is not None and not isinstance(value, str):
                raise self.fail(where, f"must be text, got {value!r}")
            return default if value is None else value
        raise TypeError(f"{where}: a {key.kind} key is read by its section's code")

    def fields(self, data: dict, path: str, cls: type, **given: Any) -> dict[str, Any]:
        """The keyword arguments of the settings dataclass ``cls`` from its section ``data``:
        each field that declares a key read as it declares (:meth:`read`), in field order;
        ``given``: the values of the fields read otherwise (a callable is called in its turn,
        so that the errors come in field order)."""
        declared = field_keys(cls)
        out = {}
        for f in dataclasses.fields(cls):
            if f.name in given:
                value = given[f.name]
                out[f.name] = value() if callable(value) else value
            elif f.name in declared:
                out[f.name] = self.read(data, path, declared[f.name])
        return out
