"""Material query: which material is the object, its density and initial parameters (SI).

    from clflow.query import query_material, load_query_result
    result = query_material("duck.png", object_name="rubber duck")        # offline knowledge base
    result = query_material("duck.png", box=(10, 20, 200, 240), backend="openai",
                            model_config=ModelConfig.resolve("http://localhost:11434/v1", "llava"))
    result.save("duck.material.json")
    guess = load_query_result("duck.material.json")     # validated with clflow.materials

Backends: "offline" matches the object name, prompt and file name against the knowledge base
shipped in clflow/data/materials_kb.json; "openai" asks any OpenAI-compatible
chat-completions endpoint with the cropped image. See docs/query.md.
"""

from clflow.query.answer import ModelAnswerError
from clflow.query.backends import BACKENDS, query_material, query_offline
from clflow.query.image import ObjectImage, crop_object
from clflow.query.knowledge import Entry, KnowledgeBase, Match, load_knowledge_base
from clflow.query.llm import ModelConfig, ModelServiceError
from clflow.query.result import QueryResult, load_query_result

__all__ = [
    "BACKENDS",
    "Entry",
    "KnowledgeBase",
    "Match",
    "ModelAnswerError",
    "ModelConfig",
    "ModelServiceError",
    "ObjectImage",
    "QueryResult",
    "crop_object",
    "load_knowledge_base",
    "load_query_result",
    "query_material",
    "query_offline",
]
