"""A config key declared once: its kind, unit, default, allowed range and meaning.

The settings dataclasses declare their fields with :func:`setting`; the keys that fill no
field of their own are :class:`Key` values in ``clflow.scene.config.schema``. The reader's
checks and the tables of docs/scene_config.md both come from them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import MISSING, dataclass
from typing import Any

# What a value can mean (docs/scene_config.md, "Ranges"): far beyond any scene's, where it
# means nothing and products of such values overflow (a domain of 1e308 m, a scale of 1e308).
LENGTH = 1e4  # m: a coordinate or size in the simulation frame (10 km)
SCENE_LENGTH = 1e9  # scene units: a coordinate or size in the splat file's frame
SCALE = (1e-6, 1e3)  # metres per scene unit
SPEED = 1e4  # m/s: a component of an initial velocity
ACCELERATION = 1e6  # m/s^2: a component of gravity or of a force stage's acceleration
FORCE = 1e9  # N: a component of a force stage's force
FPS = (1e-3, 1e6)  # frames per second
MAX_GRID = 100_000  # grid nodes along the domain's longest side (memory refuses far fewer)
MAX_PER_AXIS = 16  # fill particles per voxel and axis (16^3 = 4096 a voxel)
MAX_PIXELS = 16384  # an image's width or height: the most libx264 writes (a preview, a guidance video)
MAX_RATE = 100.0  # a learning rate, per iteration in the optimiser's units (decades for a modulus)


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


#: The default of a required key (``dataclasses.MISSING`` cannot be a dataclass field's default).
REQUIRED: Any = _Required()

#: The kinds of values a key takes; the reader checks the first seven itself
#: (``Reader.read``), the others are read by their section's own code.
KINDS = ("integer", "number", "vec3", "choice", "flag", "text", "file", "section", "list", "mapping", "other")


@dataclass(frozen=True)
class Key:
    """One key of a config section.

    ``default``: the value an absent (or null) key takes; ``REQUIRED`` for a required key (or
    one whose absence its section's code handles, ``shown`` saying what it means), None for
    an optional one. ``low``/``high`` bound numbers and integers (``strict_low``: low
    excluded); for a ``vec3``, ``high`` bounds each component's magnitude. ``unit`` is SI
    (or "scene units", "px", "deg"); ``doc`` is the meaning, as the docs' table says it;
    ``shown`` the default as the table shows it where it is no value."""

    name: str
    kind: str
    doc: str
    default: Any = REQUIRED
    unit: str = ""
    low: float | None = None
    high: float | None = None
    strict_low: bool = False
    choices: tuple[str, ...] = ()
    folder_ok: bool = False  # a file key: a folder is taken too
    shown: str | None = None

    def __post_init__(self):
        assert self.kind in KINDS, self.kind

    @property
    def required(self) -> bool:
        return self.default is REQUIRED


def setting(
    default: Any = MISSING, *, kind: str, doc: str, key: str = "", factory=None, required: bool = False, **spec
) -> Any:
    """A dataclass field declaring its config key.

    ``default`` (or ``factory()``) is the field's default and the absent key's value;
    ``required``: the key is required where its section is given (the field's default stands
    for the absent section). ``key``: the config's name for it, dotted within its section,
    where it is not the field's name. ``spec``: the other :class:`Key` attributes."""
    value = factory() if factory is not None else default
    declared = Key(key, kind, doc, REQUIRED if (required or value is MISSING) else value, **spec)
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata={"key": declared})
    if default is MISSING:
        return dataclasses.field(metadata={"key": declared})
    return dataclasses.field(default=default, metadata={"key": declared})


def field_keys(cls) -> dict[str, Key]:
    """Field name -> the key it declares, named as the config names it, of the dataclass
    ``cls``'s fields that declare one, in field order."""
    return {
        f.name: dataclasses.replace(f.metadata["key"], name=f.metadata["key"].name or f.name)
        for f in dataclasses.fields(cls)
        if "key" in f.metadata
    }


def keys_of(cls) -> tuple[Key, ...]:
    """The keys the fields of the dataclass ``cls`` declare, in field order."""
    return tuple(field_keys(cls).values())
