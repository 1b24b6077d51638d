"""Reading a model's answer: one JSON object, checked and converted with the registry.

Rules:

1. The answer is rejected (:class:`ModelAnswerError`) only when the material type cannot
   be known: no ``material``, or neither a registry type or alias nor an object the
   knowledge base files under a type ("steel" -> metal, with a warning).
2. A number that cannot be used (missing, not a JSON number, a unit that is not a unit of
   that quantity, outside the registry's valid range such as a negative modulus) takes
   the type's default from the knowledge base, with a warning.
3. Other spellings of the SI unit (MPa, cP, g/cm^3, rad) are converted, with a warning.
4. A valid value outside the registry's typical range is clamped into it, with a warning.
"""

from __future__ import annotations

from clflow.errors import ClflowError, InputError
from clflow.materials import DENSITY, MATERIALS, Param, get_material
from clflow.query.knowledge import KnowledgeBase
from clflow.query.result import STRICT_JSON, loads_strict
from clflow.query.units import si_factor

_TYPES = ", ".join(MATERIALS)


class ModelAnswerError(ClflowError):
    """The model answered, but no material can be read from the answer."""


def extract_json_object(text: str) -> tuple[dict, bool]:
    """The one JSON object in ``text`` and whether text surrounded it.

    Rule: the whole text is the object, or exactly one top-level ``{...}`` in it parses as
    JSON (prose or a Markdown fence around it is ignored). No object, or two or more, is a
    :class:`ModelAnswerError`; so is NaN/Infinity, which JSON does not allow.
    """
    stripped = text.strip()
    try:
        value = loads_strict(stripped)
    except ValueError:
        pass
    else:
        if isinstance(value, dict):
            return value, False
        raise ModelAnswerError(f"the model answered JSON but not an object: {_excerpt(stripped)}")
    objects, i = [], 0
    while (i := stripped.find("{", i)) != -1:
        try:
            obj, end = STRICT_JSON.raw_decode(stripped, i)
        except ValueError:
            i += 1
            continue
        objects.append(obj)
        i = end
    if len(objects) != 1:
        found = "no JSON object" if not objects else f"{len(objects)} JSON objects"
        raise ModelAnswerError(f"the model's answer has {found} (expected exactly one): {_excerpt(stripped)}")
    return objects[0], True


def _excerpt(text: str, n: int = 200) -> str:
    return repr(text if len(text) <= n else text[:n] + "...")


def interpret_answer(answer: dict, kb: KnowledgeBase) -> dict:
    """The :class:`QueryResult` fields material, density (kg/m^3), parameters (SI), object,
    confidence and warnings of a parsed answer, by the rules of this module's docstring;
    ``confidence`` outside [0, 1] is dropped with a warning."""
    warnings: list[str] = []
    material = _material(answer.get("material"), kb, warnings)
    defaults = kb.default_entry(material)
    density = _quantity(answer.get("density"), DENSITY, defaults.density.value, "density", warnings)
    given = answer.get("parameters")
    if not isinstance(given, dict):
        warnings.append(f"the answer has no parameters object; using the defaults of {material} ({defaults.name!r})")
        given = {}
    mat = get_material(material)
    by_name: dict[str, object] = {}
    for key, value in given.items():
        try:
            by_name[mat.param(key).name] = value
        except InputError:
            warnings.append(f"ignored parameter {key!r}: {material} has no such parameter")
    parameters = {
        p.name: _quantity(by_name.get(p.name), p, defaults.parameters[p.name].value, p.name, warnings)
        for p in mat.params
    }
    confidence = answer.get("confidence")
    if confidence is not None and not (_is_number(confidence) and 0.0 <= confidence <= 1.0):
        warnings.append(f"confidence {confidence!r} is not a number in [0, 1]; dropped")
        confidence = None
    obj = answer.get("object")
    return {
        "material": material,
        "density": density,
        "parameters": parameters,
        "object": obj if isinstance(obj, str) else None,
        "confidence": None if confidence is None else float(confidence),
        "warnings": warnings,
    }


def _is_number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _material(value: object, kb: KnowledgeBase, warnings: list[str]) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ModelAnswerError(f"the answer has no material type (got {value!r}); expected one of {_TYPES}")
    try:
        return get_material(value).name
    except InputError:
        pass
    entry = kb.identify(value)
    if entry is not None:
        warnings.append(
            f"material {value!r} is not a type; the knowledge base files {entry.name!r} under {entry.material}"
        )
        return entry.material
    raise ModelAnswerError(f"the model answered an unknown material type {value!r}; clflow knows {_TYPES}")


def _quantity(raw: object, p: Param, default: float, where: str, warnings: list[str]) -> float:
    """The SI value of one answered quantity ({"value", "unit"} or a bare number)."""
    fallback = f"; using the default {default:g} {p.unit}"
    if raw is None:
        warnings.append(f"{where} is missing{fallback}")
        return default
    value, unit = (raw.get("value"), raw.get("unit")) if isinstance(raw, dict) else (raw, None)
    if not _is_number(value):
        warnings.append(f"{where} value {value!r} is not a number{fallback}")
        return default
    if unit is None:
        warnings.append(f"{where} has no unit; read {value:g} as {p.unit}")
    else:
        factor = si_factor(str(unit), p.unit)
        if factor is None:
            warnings.append(f"{where} unit {unit!r} is not a unit of {p.unit}{fallback}")
            return default
        if factor != 1.0:
            warnings.append(f"{where}: converted {value:g} {unit} to {value * factor:g} {p.unit}")
            value *= factor
    try:
        value = p.check(value, where)
    except InputError as exc:
        warnings.append(f"{exc}{fallback}")
        return default
    lo, hi = p.typical
    if not lo <= value <= hi:
        clamped = min(max(value, lo), hi)
        warnings.append(
            f"{where} = {value:g} {p.unit} is outside the typical range [{lo:g}, {hi:g}]; clamped to {clamped:g}"
        )
        value = clamped
    return value


def cross_check(fields: dict, kb: KnowledgeBase) -> str | None:
    """The knowledge-base entry of the object the model named (None if none matches well);
    a warning in ``fields`` if the knowledge base files it under another material type."""
    entry = kb.identify(fields["object"] or "")
    if entry is None:
        return None
    if entry.material != fields["material"]:
        fields["warnings"].append(
            f"the model chose {fields['material']} for {fields['object']!r}; the knowledge base files "
            f"{entry.name!r} under {entry.material}"
        )
    return entry.name
