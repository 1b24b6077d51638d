"""The shipped knowledge base and the offline backend."""

from __future__ import annotations

import copy
import json

import pytest

from clflow.errors import InputError
from clflow.materials import DENSITY, MATERIALS, get_material
from clflow.query import load_knowledge_base, query_material
from clflow.query.knowledge import tokenize
from tests.query._helpers import assert_refuses_file

KB = load_knowledge_base()


def test_every_number_is_in_range_with_a_source():
    """Loading already checks this; here it is stated once more as a property of the file."""
    for entry in KB.entries:
        mat = get_material(entry.material)
        assert set(entry.parameters) == set(mat.param_names)
        for name, v in {"density": entry.density, **entry.parameters}.items():
            p = DENSITY if name == "density" else mat.param(name)
            assert p.typical[0] <= v.low <= v.value <= v.high <= p.typical[1], (entry.name, name)
            assert v.source in KB.sources


def test_the_issue_objects_are_covered():
    issue = [
        "rubber",
        "jelly",
        "sponge",
        "foam",
        "leaves",
        "plant",
        "flower",
        "fabric",
        "hat",
        "cable",
        "clay",
        "plasticine",
        "dough",
        "lego",
        "plastic",
        "aluminium",
        "steel",
        "copper",
        "tin can",
        "sand",
        "soil",
        "snow",
        "water",
        "honey",
        "oil",
        "jam",
        "toothpaste",
        "cream",
        "ketchup",
    ]
    for name in issue:
        assert KB.match(object_name=name), name
    assert {e.material for e in KB.entries} == set(MATERIALS)
    assert len(KB.entries) >= 40


@pytest.mark.parametrize(
    "text, material, entry",
    [
        ("rubber duck", "elastic", "rubber"),
        ("bouncy ball", "elastic", "rubber"),
        ("a wobbly jello", "elastic", "jelly"),
        ("telephone cord", "elastic", "cable"),
        ("straw hat", "elastic", "hat"),
        ("silk scarf", "elastic", "fabric"),
        ("kitchen sponge", "elastic", "sponge"),
        ("teddy bear", "elastic", "plush toy"),
        ("memory foam pillow", "foam", "foam"),
        ("alocasia", "foam", "plant"),
        ("fallen leaves", "foam", "plant"),
        ("red carnations", "foam", "flower"),
        ("a loaf of bread", "foam", "bread"),
        ("Play-Doh", "plasticine", "play-doh"),
        ("modeling clay", "plasticine", "plasticine"),
        ("pizza dough", "plasticine", "dough"),
        ("lego brick", "plasticine", "lego"),
        ("aluminum can", "metal", "soda can"),
        ("alumnium foil", "metal", "aluminium"),
        ("tin can", "metal", "tin can"),
        ("copper wire", "metal", "copper"),
        ("steel spoon", "metal", "steel"),
        ("plane propeller", "metal", "aluminium"),
        ("sandcastle", "sand", "wet sand"),
        ("pile of dry sand", "sand", "sand"),
        ("potting soil", "sand", "soil"),
        ("grains of rice", "sand", "granular food"),
        ("glass of water", "newtonian", "water"),
        ("honey dripping", "newtonian", "honey"),
        ("olive oil", "newtonian", "oil"),
        ("strawberry jam", "non_newtonian", "jam"),
        ("toothpast", "non_newtonian", "toothpaste"),
        ("whipped cream", "non_newtonian", "cream"),
        ("ketchup bottle", "non_newtonian", "ketchup"),
        ("mayo", "non_newtonian", "mayonnaise"),
        ("snowman", "snow", "snow"),
        ("a can of beans", "sand", "granular food"),
        ("a glass of milk", "newtonian", "milk"),
    ],
)
def test_offline_backend_on_object_names(text, material, entry):
    result = query_material(object_name=text)
    assert (result.material, result.matched) == (material, entry)
    assert result.confidence >= 0.85 and result.warnings == []
    e = KB.entry(entry)
    assert result.density == e.density.value and result.parameters == e.parameter_values()


def test_where_the_text_comes_from_sets_the_confidence(tmp_path):
    import cv2
    import numpy as np

    image = tmp_path / "IMG_0042-RubberDucks.jpg"
    cv2.imwrite(str(image), np.zeros((8, 8, 3), np.uint8))
    by_file = query_material(image)
    assert (by_file.matched, by_file.confidence) == ("rubber", 0.7)
    assert query_material(image, prompt="a rubber duck on a table").confidence == 0.9
    assert query_material(image, object_name="steel spoon").matched == "steel"  # the name outranks the file
    glued = query_material(prompt="rubberduck")
    assert (glued.matched, glued.confidence) == ("rubber", 0.9)


def test_longer_phrases_win_and_alternatives_are_listed():
    result = query_material(prompt="a coke can next to a steel spoon in honey")
    assert result.matched == "soda can"  # not "tin can" for the word "can"
    assert [a["entry"] for a in result.alternatives] == ["steel", "honey"]
    assert query_material(object_name="tin foil").matched == "aluminium"


def test_type_name_and_nothing_fall_back_to_documented_defaults():
    typed = query_material(prompt="some granular material")
    assert (typed.material, typed.matched, typed.confidence) == ("sand", None, 0.3)
    assert typed.parameters == KB.entry(KB.type_defaults["sand"]).parameter_values()
    assert "names the type sand" in typed.warnings[0]

    nothing = query_material(object_name="xyzzy", prompt="qwerty")
    assert (nothing.material, nothing.matched, nothing.confidence) == (KB.fallback_material, None, 0.0)
    assert nothing.density == KB.default_entry(KB.fallback_material).density.value
    assert "no knowledge-base entry matches 'xyzzy | qwerty'" in nothing.warnings[0]


def test_short_words_must_match_exactly():
    assert query_material(object_name="cap").matched == "hat"
    assert query_material(object_name="can").matched == "tin can"
    assert query_material(object_name="plane").matched is None  # not "plant"
    assert query_material(object_name="beard").matched is None  # not "bread"


def test_tokenize():
    assert tokenize("IMG_0042-RubberDucks.jpg") == ["img", "rubber", "duck", "jpg"]
    assert tokenize("Berries, boxes & glasses; Crème") == ["berry", "box", "glass", "creme"]


def _write(tmp_path, raw) -> str:
    path = tmp_path / "kb.json"
    path.write_text(json.dumps(raw))
    return path


@pytest.fixture(scope="module")
def raw_kb():
    from importlib import resources

    return json.loads((resources.files("clflow") / "data" / "materials_kb.json").read_text())


def _first(kb, *keys):
    """kb["entries"][0][keys[0]][keys[1]]..."""
    node = kb["entries"][0]
    for k in keys:
        node = node[k]
    return node


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda kb: _first(kb, "parameters").pop("poissons_ratio"),
            r"needs exactly \['youngs_modulus', 'poissons_ratio'\]",
        ),
        (lambda kb: _first(kb, "parameters", "youngs_modulus").update(value=-1.0), "outside the valid range"),
        (lambda kb: _first(kb, "parameters", "youngs_modulus").update(range=[1e6, 1e12]), "registry's typical range"),
        (lambda kb: _first(kb, "density").update(source="wikipedia"), "'wikipedia' is not a key of 'sources'"),
        (lambda kb: _first(kb).update(material="rubbery"), "unknown material 'rubbery'"),
        (lambda kb: _first(kb).update(material="jelly"), "write the registry name 'elastic'"),
        (
            lambda kb: kb["entries"][1]["aliases"].append("Rubber Ducks"),
            "alias 'Rubber Ducks' of 'silicone' already belongs to 'rubber'",
        ),
        (lambda kb: kb["type_defaults"].pop("snow"), "type_defaults must name one entry"),
        (lambda kb: kb["type_defaults"].update(snow="rubber"), "is not a snow entry"),
        (lambda kb: kb.update(version=2), "not a clflow-materials-kb file of version 1"),
    ],
)
def test_bad_knowledge_base_files(tmp_path, raw_kb, edit, message):
    raw = copy.deepcopy(raw_kb)
    edit(raw)
    with pytest.raises(InputError, match=message):
        load_knowledge_base(_write(tmp_path, raw))


@pytest.mark.parametrize(
    "name, text, match",
    [
        ("missing.json", None, "knowledge base .*missing.json not found"),
        ("bad.json", "{", "bad.json: not valid JSON"),
    ],
)
def test_unreadable_knowledge_base(tmp_path, name, text, match):
    assert_refuses_file(load_knowledge_base, tmp_path / name, text, match)


def test_a_container_is_not_the_object():
    result = query_material(prompt="a glass of water")
    assert result.matched == "water"
    assert result.alternatives == [{"entry": "glass", "material": "elastic", "confidence": 0.72, "phrase": "glass"}]


def test_every_alias_finds_its_own_entry():
    for entry in KB.entries:
        for alias in entry.aliases:
            best = KB.match(object_name=alias)[0]
            assert (best.entry.name, best.confidence) == (entry.name, 1.0), alias
