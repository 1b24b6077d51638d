"""The material query: from an image of the object (and text about it) to a material type,
a density and initial parameters, by the offline knowledge base or a foundation model."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Sequence

from clflow.errors import InputError
from clflow.query.image import crop_object
from clflow.query.knowledge import TYPE_NAME_CONFIDENCE, KnowledgeBase, load_knowledge_base
from clflow.query.llm import ModelConfig, query_model
from clflow.query.result import QueryResult

Backend = Literal["offline", "openai"]
BACKENDS = ("offline", "openai")


def query_offline(kb: KnowledgeBase, object_name: str = "", prompt: str = "", file_name: str = "") -> QueryResult:
    """Look the texts up in the knowledge base.

    The best entry gives type, density and parameters (``matched`` and ``confidence`` say
    which and how well). Without an entry, a material type named in the text ("metal",
    "granular") gives that type's default entry (confidence 0.3); without either, the
    knowledge base's fallback type's default entry (confidence 0), with a warning.
    """
    text = " | ".join(t for t in (object_name, prompt, file_name) if t)
    matches = kb.match(object_name, prompt, file_name)
    alternatives = [
        {"entry": m.entry.name, "material": m.entry.material, "confidence": m.confidence, "phrase": m.phrase}
        for m in matches[1:4]
    ]
    warnings = []
    if matches:
        best = matches[0]
        entry, confidence, obj = best.entry, best.confidence, best.phrase
    else:
        material = kb.match_type_name(object_name, prompt, file_name)
        confidence = TYPE_NAME_CONFIDENCE if material else 0.0
        entry = kb.default_entry(material or kb.fallback_material)
        named = f"it names the type {material}" if material else "it names no material type"
        warnings.append(
            f"no knowledge-base entry matches {text!r} and {named}; using the default "
            f"{entry.material} entry {entry.name!r}"
            + ("" if material else " (name the object with --name, or use the openai backend)")
        )
        obj = None
    return QueryResult(
        material=entry.material,
        density=entry.density.value,
        parameters=entry.parameter_values(),
        backend="offline",
        object=obj,
        prompt=text,
        matched=entry.name if matches else None,
        confidence=confidence,
        warnings=warnings,
        alternatives=alternatives,
    )


def query_material(
    image: str | Path | None = None,
    *,
    prompt: str = "",
    object_name: str = "",
    box: Sequence[float] | None = None,
    mask: str | Path | None = None,
    backend: Backend = "offline",
    model_config: ModelConfig | None = None,
    knowledge_base: KnowledgeBase | None = None,
) -> QueryResult:
    """Decide the material of the object in ``image``.

    Args:
        image: image file of the object (required by the "openai" backend; the offline
            backend reads only its file name, but still checks the image, box and mask).
        prompt: free text about the object or scene.
        object_name: what the object is, if known ("rubber duck").
        box: (x0, y0, x1, y1) pixel box around the object; or ``mask``: an image file
            whose nonzero pixels are the object (same size as ``image``).
        backend: "offline" (knowledge base) or "openai" (any chat-completions endpoint).
        model_config: endpoint, model and retry settings of the "openai" backend
            (default: :meth:`ModelConfig.resolve` from environment variables).
        knowledge_base: default: the one shipped with clflow.
    Returns:
        A :class:`QueryResult`; save it with ``result.save(path)``.
    """
    if backend not in BACKENDS:
        raise InputError(f"unknown backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    kb = knowledge_base or load_knowledge_base()
    if image is None:
        if backend == "openai" or box is not None or mask is not None:
            raise InputError("the openai backend, a box and a mask all need an image")
        return query_offline(kb, object_name, prompt)
    crop = crop_object(image, box, mask)
    if backend == "offline":
        result = query_offline(kb, object_name, prompt, Path(image).stem)
    else:
        result = query_model(crop, model_config or ModelConfig.resolve(), kb, prompt, object_name)
    result.image, result.crop_box = str(image), list(crop.box)
    return result
