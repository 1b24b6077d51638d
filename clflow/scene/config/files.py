"""Config files: strict YAML and JSON (a key given twice refused, ``2e4`` a number, the
nesting and a YAML file's aliases bounded), the CLI's ``--set`` overrides, and load_config."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Sequence

from clflow.errors import InputError
from clflow.fileio.reading import MAX_NESTING, NestingError, parse_json
from clflow.scene.config.parse import parse_config
from clflow.scene.config.settings import SceneConfig


def _dotted(path: str, key: object) -> str:
    """``path`` extended by a mapping key (``a.b``) or a list index (``a[0]``)."""
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else str(key)


class _JsonPairs(list):
    """A JSON object as its (key, value) pairs, so duplicate keys survive parsing."""


def _json_without_duplicates(value: Any, path: str = "") -> Any:
    """Turn parsed :class:`_JsonPairs` into dicts; a key given twice raises with its dotted path."""
    if isinstance(value, _JsonPairs):
        out: dict[str, Any] = {}
        for key, item in value:
            if key in out:
                raise DuplicateKeyError(_dotted(path, key))
            out[key] = _json_without_duplicates(item, _dotted(path, key))
        return out
    if isinstance(value, list):
        return [_json_without_duplicates(item, _dotted(path, i)) for i, item in enumerate(value)]
    return value


class DuplicateKeyError(Exception):
    """A mapping key given twice; the argument is its dotted path (and YAML line)."""


class StructureError(Exception):
    """A YAML document refused before it is built: nested too deep, its aliases expanding
    it too far or into itself; the argument says where and why."""


#: The most nodes (mappings, lists, keys and values) a YAML document may have with its
#: aliases expanded: hundreds of times a large config, a tiny part of the 9^9 of a
#: "billion laughs" of nested aliases, which every walk of the result would follow.
MAX_YAML_NODES = 100_000


def read_json(text: str) -> Any:
    return _json_without_duplicates(parse_json(text, object_pairs_hook=_JsonPairs))


#: A number with an exponent that YAML 1.1 (PyYAML) reads as a string: no dot (``2e4``) or
#: no sign in the exponent (``2.0e4``). YAML 1.2 and JSON read them as numbers, and so do we.
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")


def read_yaml(text: str) -> Any:
    """``yaml.safe_load`` that reads ``2e4`` as a float and rejects a mapping key given twice
    (PyYAML keeps the last), nesting deeper than MAX_NESTING levels and aliases that expand
    the document past MAX_YAML_NODES nodes or into itself (StructureError)."""
    import yaml

    class StrictLoader(yaml.SafeLoader):
        depth = 0  # the lists and mappings open where the composer is

        def compose_node(self, parent, index):
            opens = self.check_event(yaml.SequenceStartEvent, yaml.MappingStartEvent)
            if opens and self.depth == MAX_NESTING:  # before PyYAML's recursive composer runs out of stack
                raise StructureError(f"nested deeper than {MAX_NESTING} levels ({_where(self.peek_event())})")
            self.depth += opens
            try:
                return super().compose_node(parent, index)
            finally:
                self.depth -= opens

        def construct_document(self, node):
            _check_tree(node)
            return super().construct_document(node)

        def construct_object(self, node, deep=False):
            try:
                return super().construct_object(node, deep)
            except (ValueError, KeyError, AttributeError) as exc:  # PyYAML's: 2001-13-45, !!bool maybe
                if not isinstance(node, yaml.ScalarNode):
                    raise
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"{_shown(node.value)} cannot be read as a YAML {node.tag.rpartition(':')[2]}{_why(exc)}",
                    node.start_mark,
                ) from None

    StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789."))
    return yaml.load(text, Loader=StrictLoader)


def _shown(text: str) -> str:
    """``text`` quoted, or its start and length when long."""
    return repr(text) if len(text) <= 40 else f"{text[:20]!r}... ({len(text):,} characters)"


def _why(exc: Exception) -> str:
    """A ValueError's reason, without Python's advice (sys.set_int_max_str_digits)."""
    return f" ({str(exc).split(';')[0]})" if isinstance(exc, ValueError) else ""


def _where(node) -> str:
    """Where a YAML node or event starts: line and column."""
    return f"line {node.start_mark.line + 1}, column {node.start_mark.column + 1}"


def _check_tree(root) -> None:
    """Refuse a composed YAML document with a mapping key given twice (DuplicateKeyError),
    or whose aliases nest it deeper than MAX_NESTING levels, expand it past MAX_YAML_NODES
    nodes or into itself (StructureError). Each node is walked once, at its first place
    (an alias comes after its anchor), and counted by its size wherever an alias repeats
    it, so a "billion laughs" is refused as fast as its text is read."""
    import yaml

    sizes: dict[int, tuple[int, int]] = {}  # id(node) -> (nodes, levels of lists and mappings), aliases expanded
    open_nodes: set[int] = set()

    def walk(node, path: str, depth: int) -> int:
        """The nodes of ``node``, ``depth`` lists and mappings down, aliases expanded."""
        where = path or "the document"
        if id(node) in open_nodes:
            raise StructureError(f"{where}: an alias to a node that holds it ({_where(node)}): it would nest endlessly")
        if id(node) not in sizes:
            open_nodes.add(id(node))
            children = []
            if isinstance(node, yaml.MappingNode):
                seen = set()
                for key_node, value_node in node.value:
                    key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                    if key is not None and key != "<<":
                        if key in seen:
                            raise DuplicateKeyError(f"{_dotted(path, key)} (line {key_node.start_mark.line + 1})")
                        seen.add(key)
                    children += [(key_node, path), (value_node, _dotted(path, key))]
            elif isinstance(node, yaml.SequenceNode):
                children = [(item, _dotted(path, i)) for i, item in enumerate(node.value)]
            count, levels = 1, 0
            for child, child_path in children:
                count += walk(child, child_path, depth + 1)
                levels = max(levels, sizes[id(child)][1])
                if count > MAX_YAML_NODES:
                    raise StructureError(
                        f"{where}: more than {MAX_YAML_NODES:,} nodes (lists, mappings, keys and values) with its "
                        f"aliases expanded: too many to read (an alias bomb?); write fewer aliases"
                    )
            open_nodes.discard(id(node))
            sizes[id(node)] = count, levels + isinstance(node, yaml.CollectionNode)
        count, levels = sizes[id(node)]
        if depth + levels > MAX_NESTING:
            raise StructureError(f"{where}: nested deeper than {MAX_NESTING} levels with its aliases expanded")
        return count

    walk(root, "", 0)


def read_data_file(path: str | Path, what: str) -> Any:
    """The parsed JSON (a .json file) or YAML of the user's ``what`` file at ``path`` (None
    when it holds nothing); InputError, one line naming the file, where and what is wrong,
    when it cannot be read, does not parse or gives a key twice."""
    import yaml

    from clflow.fileio import read_text

    path = Path(path)
    text = read_text(path, what)
    try:
        return read_json(text) if path.suffix.lower() == ".json" else read_yaml(text)
    except (NestingError, StructureError) as exc:
        raise InputError(f"{path}: {exc}") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: not valid JSON: line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML: {_yaml_problem(exc)}") from None
    except DuplicateKeyError as exc:
        raise InputError(f"{path}: {exc}: duplicate key (each key may appear only once)") from None


def _yaml_problem(exc: Exception) -> str:
    """A YAML parser's error as one line: where (line, column) and what."""
    mark, problem = getattr(exc, "problem_mark", None), getattr(exc, "problem", None)
    if mark is None or not problem:
        return " ".join(str(exc).split())
    return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"


def load_config(path: str | Path, overrides: Sequence[str] = ()) -> SceneConfig:
    """Read and validate a YAML (.yaml/.yml) or JSON (.json) scene config.

    ``overrides``: ``key.sub=value`` strings (the CLI's ``--set``), each value read as YAML
    (``2e4``, ``[0, 1, 0]``, ``auto``), set over the file's before the whole is validated.
    """
    path = Path(path)
    data = read_data_file(path, "config")
    if data is None or data == {}:  # before the --set keys make it look like a config lacking keys
        raise InputError(f"{path}: the config file is empty")
    keys = {}
    for item in overrides:
        keys[_override(data, item)] = item
    try:
        return parse_config(data, str(path), path.parent.resolve())
    except InputError as exc:
        # name the --set that brought in the bad key or value, not only the file
        where = str(exc).removeprefix(f"{path}: ").split(":")[0]
        for key, item in keys.items():
            if key == where or key.startswith((where + ".", where + "[")) or where.startswith((key + ".", key + "[")):
                raise InputError(f"--set {item}: {str(exc).removeprefix(f'{path}: ')}") from None
        raise


def _named_object(objects: Any, name: str, item: str) -> dict:
    """The entry of ``objects`` (a list of entries with names, or a mapping of names to
    entries) named ``name``; InputError naming the objects there are when none is."""
    if isinstance(objects, dict):
        names, entry = list(objects), objects.get(name)
    else:
        named = [o for o in objects if isinstance(o, dict)]
        names = [o.get("name") for o in named]
        entry = next((o for o in named if o.get("name") == name), None)
    if not isinstance(entry, dict):
        listed = ", ".join(str(n) for n in names) or "none"
        raise InputError(f"--set {item}: the config has no object named {name!r} (its objects: {listed})")
    return entry


def _override(data: Any, item: str) -> str:
    """Set ``key.sub=value`` (value read as YAML) in the parsed config ``data``, making the
    mappings on the way; a number as a part indexes an existing list item (``forces.0.end``),
    a name after ``objects`` an existing object (``objects.jelly.velocity``). Returns the key
    as the config's messages write it (``forces[0].end``)."""
    import yaml

    key, sep, text = item.partition("=")
    parts = key.strip().split(".")
    if not sep or not all(re.fullmatch(r"[A-Za-z0-9_]+", p) for p in parts) or parts[0].isdigit():
        raise InputError(
            f"--set {item}: expected KEY.SUB=VALUE with a dotted key of config names (a number "
            f"for a list item), e.g. simulation.frames=24 or forces.0.end=0.5"
        )
    try:
        value = read_yaml(text)
    except (yaml.YAMLError, DuplicateKeyError, StructureError) as exc:
        raise InputError(f"--set {item}: the value is not valid YAML ({' '.join(str(exc).split())})") from None
    node, walked = data, ""
    for k, part in enumerate(parts):
        last = k == len(parts) - 1
        if walked == "objects" and not (isinstance(node, list) and part.isdigit()):  # an object by its name
            node = _named_object(node, part, item)
            walked += f".{part}"
            if last:
                raise InputError(f"--set {item}: set a key of the object (objects.{part}.material...), not all of it")
            continue
        if part == "objects" and not walked and not last and isinstance(data, dict) and data.get("objects") is None:
            given = "one object (object and material)" if "object" in data or "material" in data else "no objects"
            raise InputError(
                f"--set {item}: the config gives {given}, so there is no object {parts[1]!r} to set"
                + (": set object.* and material.* keys" if "object" in data or "material" in data else "")
            )
        if isinstance(node, list) and part.isdigit():
            index = int(part)
            if index >= len(node):
                raise InputError(
                    f"--set {item}: {walked} has {len(node)} item(s), so no item {index} "
                    f"(items count from 0; add new ones in the config file)"
                )
            if last:
                node[index] = value
            else:
                node = node[index]
            walked += f"[{index}]"
            continue
        if not isinstance(node, dict):
            where = walked or "the config"
            raise InputError(f"--set {item}: {where} is a {type(node).__name__} in the config, not a mapping of keys")
        if last:
            node[part] = value
        else:
            if node.get(part) is None:
                if parts[k + 1].isdigit():
                    raise InputError(
                        f"--set {item}: {walked + '.' if walked else ''}{part} is not in the config: "
                        f"set the whole list ({walked + '.' if walked else ''}{part}=[...])"
                    )
                node[part] = {}
            node = node[part]
        walked += f".{part}" if walked else part
    return walked
