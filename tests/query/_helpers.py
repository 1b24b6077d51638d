"""Helpers the material query tests share."""

from __future__ import annotations

from pathlib import Path

import pytest

from clflow.errors import InputError


def assert_refuses_file(load, path: Path, text: str | None, match: str) -> None:
    """``load(path)`` raises InputError matching ``match`` once ``path`` holds ``text`` (None: no file)."""
    if text is not None:
        path.write_text(text)
    with pytest.raises(InputError, match=match):
        load(path)
