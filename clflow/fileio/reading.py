"""Reading users' files: text, JSON and numpy arrays, each refused in one line (InputError
naming the file and the problem) when it cannot be read as what it should be."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

#: The deepest nesting of lists and mappings read from a user's JSON or YAML file: far more
#: than any config or record has, far less than where Python's recursion (the parsers' and
#: every walk of what they return) runs out.
MAX_NESTING = 100

# a JSON string (its brackets are text) or a bracket
_JSON_NESTING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"|[][{}]')


class NestingError(json.JSONDecodeError):
    """JSON text nested deeper than MAX_NESTING levels, at the bracket that goes too deep."""

    def __str__(self) -> str:
        return f"{self.msg} (line {self.lineno}, column {self.colno})"


def parse_json(text: str, **kwargs):
    """``json.loads(text, **kwargs)``, but a :class:`NestingError` (a JSONDecodeError) where
    the text nests lists and objects deeper than MAX_NESTING levels, before it is parsed, and
    a JSONDecodeError for a number too long for Python to read (json's is a plain ValueError)."""
    depth = 0
    for match in _JSON_NESTING.finditer(text):
        bracket = match.group()
        if bracket in ("[", "{"):
            depth += 1
            if depth > MAX_NESTING:
                raise NestingError(f"nested deeper than {MAX_NESTING} levels", text, match.start())
        elif bracket in ("]", "}"):
            depth -= 1
    try:
        return json.loads(text, **kwargs)
    except ValueError as exc:
        if isinstance(exc, json.JSONDecodeError) or "integer string conversion" not in str(exc):
            raise
        digits = sys.get_int_max_str_digits()
        long = re.search(rf"[0-9]{{{digits + 1},}}", text)
        raise json.JSONDecodeError(
            f"a number of {len(long.group()):,} digits (at most {digits:,})", text, long.start()
        ) from None


def read_text(path: str | os.PathLike, what: str = "file") -> str:
    """The text of a user's file (UTF-8, a byte-order mark allowed); InputError, one line
    naming ``what`` and the path, when it cannot be read or is not UTF-8 text."""
    from clflow.errors import InputError

    path = Path(path)
    try:
        data = path.read_bytes()
    except IsADirectoryError:
        raise InputError(f"{what} {path} is a folder, not a file") from None
    except FileNotFoundError:
        raise InputError(f"{what} {path} not found") from None
    except OSError as exc:
        raise InputError(f"cannot read {what} {path}: {exc.strerror}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(
            f"{what} {path} is not UTF-8 text (byte 0x{data[exc.start]:02x} on line {line}); save it as UTF-8"
        ) from None


def read_json(path: str | os.PathLike, what: str = "file", expected: str = ""):
    """The parsed JSON of a user's file (:func:`read_text`; NaN and Infinity refused, as JSON
    does); InputError, one line with the path, line and column, when it is not JSON or nests
    deeper than MAX_NESTING levels (``expected``: what the file should have been, added to
    the message)."""
    from clflow.errors import InputError

    def not_a_number(name: str):
        raise json.JSONDecodeError(f"{name} is not a number JSON allows", name, 0)

    text = read_text(path, what)
    try:
        return parse_json(text, parse_constant=not_a_number)
    except NestingError as exc:
        raise InputError(f"{path}: {exc}{'; ' + expected if expected else ''}") from None
    except json.JSONDecodeError as exc:
        where = f"line {exc.lineno}, column {exc.colno}: " if exc.doc is text else ""
        raise InputError(f"{path}: not valid JSON: {where}{exc.msg}{'; ' + expected if expected else ''}") from None


def load_arrays(path: str | os.PathLike, what: str = "array file") -> dict[str, np.ndarray]:
    """The arrays of an .npz (by name) or an .npy (as ``{"array": a}``), read in full; a file
    that is empty, truncated, not numpy's or holds Python objects is an InputError."""
    import zipfile
    import zlib

    import numpy as np

    from clflow.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    with open(path, "rb") as fh:
        head = fh.read(6)
    if not head:
        raise InputError(f"{path}: the {what} is empty (0 bytes)")
    if head[:2] != b"PK" and head != b"\x93NUMPY":
        raise InputError(f"{path}: not a numpy .npz/.npy {what}")
    try:
        if head == b"\x93NUMPY":
            return {"array": np.load(path, allow_pickle=False)}
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except ValueError as exc:
        if "pickle" in str(exc):  # npz: "pickled (object) data", npy: "allow_pickle=False"
            raise InputError(
                f"{path}: the {what} holds Python objects, not plain arrays; refusing to unpickle"
            ) from None
        raise InputError(f"{path}: damaged or truncated {what} ({exc})") from None
    except (EOFError, OSError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"{path}: damaged or truncated {what} ({type(exc).__name__}: {exc})") from None
