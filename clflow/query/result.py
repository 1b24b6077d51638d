"""The result record of a material query: a small JSON file the optimiser reads as its
initial guess. Names and units are the registry's (:mod:`clflow.materials`).

    {"format": "clflow-material-query", "version": 1,
     "material": "elastic", "density": 1100.0,
     "parameters": {"youngs_modulus": 5e6, "poissons_ratio": 0.49},
     "units": {"density": "kg/m^3", "youngs_modulus": "Pa", "poissons_ratio": "1"},
     "object": "rubber duck", "backend": "offline", "model": null, "prompt": "...",
     "raw_answer": null, "matched": "rubber", "confidence": 0.9, "warnings": [], ...}
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from clflow.errors import InputError
from clflow.fileio import atomic_write_text
from clflow.materials import DENSITY, get_material, validate_params

RESULT_FORMAT = "clflow-material-query"
RESULT_VERSION = 1


@dataclass
class QueryResult:
    """What the query decided and how.

    ``material`` is a registry type, ``density`` in kg/m^3, ``parameters`` every parameter
    of the type in SI units. ``backend`` is "offline" or "openai"; ``model`` the model name
    (None offline); ``prompt`` the text asked or matched; ``raw_answer`` the model's reply
    verbatim (None offline); ``matched`` the knowledge-base entry of the object (offline:
    the match; openai: the object the model named; None if none matches); ``confidence``
    in [0, 1] (match strength offline, the model's own estimate online, None if it gave
    none); ``warnings`` everything the query had to assume, clamp or convert;
    ``alternatives`` other entries the offline backend found; ``crop_box`` the pixel box
    (x0, y0, x1, y1) the model saw. The API key is never part of it.
    """

    material: str
    density: float
    parameters: dict[str, float]
    backend: str
    object: str | None = None
    model: str | None = None
    prompt: str = ""
    raw_answer: str | None = None
    matched: str | None = None
    confidence: float | None = None
    warnings: list[str] = field(default_factory=list)
    alternatives: list[dict] = field(default_factory=list)
    image: str | None = None
    crop_box: list[int] | None = None
    structured_output: bool | None = None

    @property
    def units(self) -> dict[str, str]:
        mat = get_material(self.material)
        return {"density": DENSITY.unit, **{p.name: p.unit for p in mat.params}}

    def to_dict(self) -> dict:
        d = asdict(self)
        head = {"format": RESULT_FORMAT, "version": RESULT_VERSION}
        return {**head, **{k: d.pop(k) for k in ("material", "density", "parameters")}, "units": self.units, **d}

    def save(self, path: str | Path) -> Path:
        """Write the record as JSON, atomically; returns the path."""
        path = Path(path)
        atomic_write_text(path, json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n")
        return path


def load_query_result(path: str | Path) -> QueryResult:
    """Read a query record and validate it with the material registry.

    The material must be a registry type (aliases become the canonical name), the density
    and parameters must be in their valid ranges, and a ``units`` table, if present, must
    give the registry's unit of every quantity. Parameters the file leaves out take the
    registry's defaults. Problems raise :class:`InputError` naming the file and key.
    """
    from clflow.fileio import read_text
    from clflow.fileio.reading import NestingError, parse_json

    path = Path(path)
    text = read_text(path, "query result")
    try:
        raw = parse_json(text, parse_constant=_reject_constant)
    except NestingError as exc:
        raise InputError(f"{path}: {exc}") from None
    except (json.JSONDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(raw, dict) or raw.get("format") != RESULT_FORMAT:
        raise InputError(f'{path}: not a material query result (expected "format": "{RESULT_FORMAT}")')
    if raw.get("version") != RESULT_VERSION:
        raise InputError(f"{path}: version {raw.get('version')!r} is not supported (expected {RESULT_VERSION})")
    for key in ("material", "density", "parameters", "backend"):
        if key not in raw:
            raise InputError(f"{path}: missing key {key!r}")
    if not isinstance(raw["material"], str):
        raise InputError(f"{path}: material must be a string, got {raw['material']!r}")
    if not isinstance(raw["parameters"], dict):
        raise InputError(f"{path}: parameters must be an object of name: value, got {raw['parameters']!r}")
    material = get_material(raw["material"]).name
    where = f"{path}: {material}"
    density = DENSITY.check(raw["density"], f"{path}")
    parameters = validate_params(material, raw["parameters"], where)
    units = raw.get("units")
    if units is not None:
        expected = QueryResult(material, density, parameters, "").units
        for key, unit in units.items():
            if key not in expected:
                raise InputError(f"{path}: units lists {key!r}, which {material} does not have")
            if unit != expected[key]:
                raise InputError(f"{path}: units[{key!r}] is {unit!r}; clflow uses SI: {expected[key]!r}")
    known = {f for f in QueryResult.__dataclass_fields__} - {"material", "density", "parameters"}
    extra = {k: raw[k] for k in known if k in raw}
    confidence = extra.get("confidence")
    if confidence is not None and not (isinstance(confidence, (int, float)) and 0.0 <= confidence <= 1.0):
        raise InputError(f"{path}: confidence must be a number in [0, 1], got {confidence!r}")
    return QueryResult(material=material, density=density, parameters=parameters, **extra)


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number JSON allows")


# Python's json accepts NaN and Infinity; JSON does not, and neither does clflow.
STRICT_JSON = json.JSONDecoder(parse_constant=_reject_constant)


def loads_strict(text: str | bytes):
    """``json.loads`` that rejects NaN and Infinity."""
    return json.loads(text, parse_constant=_reject_constant)
