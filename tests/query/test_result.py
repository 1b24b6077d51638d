"""The result record: JSON layout, atomic save, and the validating loader."""

from __future__ import annotations

import json

import pytest

from clflow.errors import InputError
from clflow.fileio import WRITTEN_RECORD
from clflow.query import QueryResult, load_query_result, query_material
from tests.query._helpers import assert_refuses_file


def test_round_trip_uses_registry_names_and_units(tmp_path):
    result = query_material(object_name="strawberry jam", prompt="jam sliding off toast")
    path = result.save(tmp_path / "out" / "jam.json")
    raw = json.loads(path.read_text())
    assert raw["format"] == "clflow-material-query" and raw["material"] == "non_newtonian"
    assert raw["units"] == {
        "density": "kg/m^3",
        "shear_modulus": "Pa",
        "bulk_modulus": "Pa",
        "yield_stress": "Pa",
        "viscosity": "Pa*s",
    }
    assert {"backend", "model", "prompt", "raw_answer", "matched", "confidence", "warnings"} <= set(raw)
    assert load_query_result(path) == result
    assert sorted(p.name for p in tmp_path.joinpath("out").iterdir()) == [WRITTEN_RECORD, "jam.json"]  # no temporary


def test_loader_accepts_aliases_and_fills_defaults(tmp_path):
    path = tmp_path / "hand.json"
    path.write_text(
        json.dumps(
            {
                "format": "clflow-material-query",
                "version": 1,
                "material": "Jelly",
                "density": 1050,
                "parameters": {"E": 2e4},
                "backend": "hand",
            }
        )
    )
    loaded = load_query_result(path)
    assert loaded.material == "elastic"
    assert loaded.parameters == {"youngs_modulus": 2e4, "poissons_ratio": 0.3}


def _record(**changes) -> dict:
    base = QueryResult("elastic", 1100.0, {"youngs_modulus": 5e6, "poissons_ratio": 0.45}, "offline").to_dict()
    base.update(changes)
    return base


@pytest.mark.parametrize(
    "record, message",
    [
        (_record(format="something"), "not a material query result"),
        (_record(version=7), "version 7 is not supported"),
        ({k: v for k, v in _record().items() if k != "density"}, "missing key 'density'"),
        (_record(material="gel"), "unknown material 'gel'"),
        (_record(density=-3.0), r"density \(rho\) = -3 kg/m\^3 is outside the valid range"),
        (_record(parameters={"poissons_ratio": 0.5}), r"poissons_ratio \(nu\) = 0.5 is outside the valid range"),
        (_record(parameters={"viscosity": 1.0}), "material 'elastic' has no parameter 'viscosity'"),
        (_record(parameters={"youngs_modulus": "soft"}), "youngs_modulus must be a number, got 'soft'"),
        (_record(units={"density": "g/cm^3"}), r"units\['density'\] is 'g/cm\^3'; clflow uses SI: 'kg/m\^3'"),
        (_record(units={"viscosity": "Pa*s"}), "units lists 'viscosity', which elastic does not have"),
        (_record(confidence=3), r"confidence must be a number in \[0, 1\]"),
    ],
)
def test_loader_rejects_bad_records(tmp_path, record, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(record))
    with pytest.raises(InputError, match=message):
        load_query_result(path)


@pytest.mark.parametrize(
    "name, text, match",
    [
        ("none.json", None, "query result .*none.json not found"),
        ("nan.json", '{"density": NaN}', "nan.json: not valid JSON: NaN"),
        ("list.json", "[]", "not a material query result"),
    ],
)
def test_loader_rejects_unreadable_files(tmp_path, name, text, match):
    assert_refuses_file(load_query_result, tmp_path / name, text, match)


def test_save_refuses_non_finite_numbers(tmp_path):
    result = QueryResult("elastic", float("nan"), {"youngs_modulus": 1e6}, "offline")
    with pytest.raises(ValueError):
        result.save(tmp_path / "x.json")
    assert not list(tmp_path.iterdir())
